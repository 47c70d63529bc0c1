"""Image reading with clear errors: cv2.imread returns None (or asserts later) on a bad file, we raise instead."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .base import DatasetError


def _read_bytes(path: Path, what: str) -> np.ndarray:
    try:
        return np.frombuffer(path.read_bytes(), dtype=np.uint8)
    except FileNotFoundError as exc:
        raise DatasetError(f"{what} missing: {path}") from exc
    except OSError as exc:
        raise DatasetError(f"cannot read {what} {path}: {exc}") from exc


def read_rgb(path: str | Path) -> np.ndarray:
    """HxWx3 uint8 in RGB order (OpenCV reads BGR); DatasetError when missing, undecodable or truncated.

    A truncated JPEG decodes "successfully" with a grey lower part (libjpeg only warns), so JPEGs must
    also end with the end-of-image marker.
    """
    path = Path(path)
    data = _read_bytes(path, "colour image")
    if data[:2].tobytes() == b"\xff\xd8" and b"\xff\xd9" not in data[-64:].tobytes():
        raise DatasetError(f"truncated JPEG (no end-of-image marker): {path}")
    image = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if image is None or image.ndim != 3 or image.shape[2] != 3 or image.size == 0:
        raise DatasetError(f"cannot decode colour image (corrupt or not an image): {path}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_depth_u16(path: str | Path) -> np.ndarray:
    """HxW uint16 depth PNG as stored; DatasetError when missing, undecodable or not 16-bit single channel."""
    path = Path(path)
    data = _read_bytes(path, "depth image")
    depth = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if depth is None or depth.size == 0:
        raise DatasetError(f"cannot decode depth image (corrupt or not an image): {path}")
    if depth.ndim != 2 or depth.dtype != np.uint16:
        raise DatasetError(f"depth image must be single-channel uint16, got {depth.dtype} {depth.shape}: {path}")
    return depth


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image file, decoding it once (used to fill Intrinsics)."""
    image = read_rgb(path)
    return int(image.shape[1]), int(image.shape[0])
