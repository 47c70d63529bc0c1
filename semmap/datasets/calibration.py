"""The camera a run uses, said before the first frame and checked against the data.

A wrong calibration does not fail anything by itself: a depth factor 5x off maps a chair 13 m away, the intrinsics
of another camera move every object by a metre, and nothing complains. So `semmap run` states where its intrinsics
and depth scale come from (camera.yaml, intrinsics.txt, camera-intrinsics.txt or a reader's built-in default) and
checks them against the frames first (`check_calibration`, pure: no I/O):

- the principal point lies inside the image (refused otherwise, naming the file and the keys);
- the image size the intrinsics imply (about 2cx x 2cy, or the file's own width/height) matches the frames
  (refused otherwise: e.g. a 1280x960 camera's cx, cy on 640x480 frames);
- the depth scale puts most depth where indoor depth lies (0.3-10 m): far off (median beyond 0.05-50 m, e.g.
  `depth_factor: 1` on 5000-unit PNGs) is refused, off (e.g. 1000 on 5000-unit PNGs: median ~5x too far) is a
  warning that names the factor that fits.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .base import Dataset, DatasetError, Intrinsics

INDOOR_M = (0.3, 10.0)  # where most depth of an indoor RGB-D camera lies
REFUSE_MEDIAN_M = (0.05, 50.0)  # a median depth outside this is no indoor camera's: the scale is wrong
IN_BAND_MIN = 0.8  # the fraction of valid depth that should lie in INDOOR_M
COMMON_FACTORS = (1000.0, 5000.0)  # depth PNG units per metre: millimetres (Kinect, RealSense), TUM's 1/5000 m
SIZE_TOLERANCE = 0.25  # 2cx (2cy) within 25 % of the width (height); real principal points sit near the centre
SAMPLE_FRAMES = 5


class CalibrationError(DatasetError):
    """The calibration contradicts the data (the message names the file and the key)."""


@dataclass(frozen=True)
class CameraSource:
    """Where a dataset's calibration comes from, for the banner and for the messages that name it."""

    intrinsics_from: str  # e.g. "/data/x/camera.yaml" or "built-in default (TUM fr2)"
    depth_from: str = ""  # e.g. "/data/x/camera.yaml, key depth_factor" ("" where the reader decides the units)
    intrinsics_keys: str = "cx, cy"  # how the file names the principal point
    depth_key: str = ""  # the key that sets the depth scale (depth_factor, ...)
    declared_size: tuple[int, int] | None = None  # (width, height) where the file states it
    check_depth: bool = False  # depth read from files with a declared or assumed scale (not computed)


def depth_statistics(depths: Sequence[np.ndarray], depth_scale: float) -> tuple[float, float, int]:
    """(median depth in metres, fraction of valid pixels in INDOOR_M, valid pixels) over the sampled frames."""
    valid = [d[d > 0].astype(np.float64) * depth_scale for d in depths]
    values = np.concatenate(valid) if valid else np.zeros(0)
    if values.size == 0:
        return float("nan"), 0.0, 0
    in_band = float(np.mean((values >= INDOOR_M[0]) & (values <= INDOOR_M[1])))
    return float(np.median(values)), in_band, int(values.size)


def suggest_factor(depths: Sequence[np.ndarray]) -> float | None:
    """The common depth factor (units per metre) that puts the most depth in INDOOR_M, if one puts enough."""
    best = max(COMMON_FACTORS, key=lambda f: depth_statistics(depths, 1.0 / f)[1])
    return best if depth_statistics(depths, 1.0 / best)[1] >= IN_BAND_MIN else None


def check_calibration(intrinsics: Intrinsics, depth_scale: float, frame_size: tuple[int, int],
                      depths: Sequence[np.ndarray], source: CameraSource) -> list[str]:
    """Warnings for a calibration that looks off; CalibrationError for one that contradicts the data.
    `frame_size` is the frames' (width, height); `depths` a few raw depth images (uint16 units)."""
    width, height = frame_size
    where = source.intrinsics_from
    cx, cy = intrinsics.cx, intrinsics.cy
    if not (0.0 < cx < width and 0.0 < cy < height):
        raise CalibrationError(
            f"{where}: the principal point ({source.intrinsics_keys} = {cx:g}, {cy:g}) lies outside the "
            f"{width}x{height} frames: these intrinsics are not this camera's")
    if source.declared_size is not None and tuple(source.declared_size) != (width, height):
        w, h = source.declared_size
        raise CalibrationError(f"{where}: the calibration is for {w}x{h} images (its width, height) but the frames "
                               f"are {width}x{height}: give this camera's intrinsics")
    implied = (2.0 * cx, 2.0 * cy)
    if abs(implied[0] - width) > SIZE_TOLERANCE * width or abs(implied[1] - height) > SIZE_TOLERANCE * height:
        raise CalibrationError(
            f"{where}: the principal point ({source.intrinsics_keys} = {cx:g}, {cy:g}) implies images of about "
            f"{implied[0]:.0f}x{implied[1]:.0f}, but the frames are {width}x{height}: these intrinsics are another "
            "camera's (or another resolution's)")
    warnings: list[str] = []
    if not source.check_depth or not depths:
        return warnings
    median, in_band, count = depth_statistics(depths, depth_scale)
    if count == 0:
        return [f"no valid depth in the {len(depths)} frames sampled: the depth scale ({source.depth_from}) "
                "could not be checked"]
    factor = 1.0 / depth_scale
    suggested = suggest_factor(depths)
    hint = (f"; {source.depth_key or 'the depth factor'} {suggested:g} would give a median of "
            f"{depth_statistics(depths, 1.0 / suggested)[0]:.2f} m" if suggested and suggested != factor else "")
    what = (f"{source.depth_from}: depth factor {factor:g} units per metre gives a median depth of {median:.3g} m "
            f"over {len(depths)} frames ({100 * in_band:.0f} % within {INDOOR_M[0]}-{INDOOR_M[1]:g} m, where most "
            f"indoor depth lies){hint}")
    if not REFUSE_MEDIAN_M[0] <= median <= REFUSE_MEDIAN_M[1]:
        raise CalibrationError(what)
    if in_band < IN_BAND_MIN and (suggested is None or suggested != factor):
        warnings.append(what)
    return warnings


def camera_source(dataset: Dataset) -> CameraSource:
    """The dataset's own account of its calibration, or a generic one for readers that have none."""
    source = getattr(dataset, "camera_source", None)
    if callable(source):
        return source()
    return CameraSource(intrinsics_from=f"the {dataset.name} reader")


def sample_depths(dataset: Dataset, count: int = SAMPLE_FRAMES) -> tuple[list[np.ndarray], tuple[int, int] | None]:
    """Raw depth of up to `count` frames spread over the dataset (unreadable ones left out), and the frames'
    (width, height)."""
    n = len(dataset)
    depths, size = [], None
    for index in sorted({int(i) for i in np.linspace(0, n - 1, min(count, n))}):
        try:
            frame = dataset[index]
        except DatasetError:
            continue
        depths.append(frame.depth)
        size = size or (int(frame.rgb.shape[1]), int(frame.rgb.shape[0]))
    return depths, size


def check_dataset_camera(dataset: Dataset, count: int = SAMPLE_FRAMES) -> tuple[str, list[str]]:
    """(the camera line for the run's banner, warnings) for an opened dataset; CalibrationError on a calibration
    that contradicts its frames. Reads `count` frames."""
    source = camera_source(dataset)
    intrinsics: Intrinsics | None = getattr(dataset, "intrinsics", None)
    depths, size = sample_depths(dataset, count if source.check_depth else 1)  # (bags: no seeking about)
    if intrinsics is None or size is None:
        return f"camera: from the {dataset.name} reader (per frame)", []
    scale = float(getattr(dataset, "depth_scale", 0.0) or 0.0)
    warnings = check_calibration(intrinsics, scale, size, depths, source) if scale > 0 else []
    depth = f", depth {1.0 / scale:g} units per metre ({source.depth_from or 'the reader'})" if scale > 0 else ""
    line = (f"camera: {source.intrinsics_from}: fx {intrinsics.fx:g} fy {intrinsics.fy:g} cx {intrinsics.cx:g} "
            f"cy {intrinsics.cy:g}, {size[0]}x{size[1]}{depth}")
    return line, warnings
