"""Image reading with clear errors: cv2.imread returns None (or asserts later) on a bad file, we raise instead."""

from __future__ import annotations

import zlib
from pathlib import Path

import cv2
import numpy as np

from semmap.core.messages import DEPTH_NO_READING

from .base import DatasetError, EncodedImage

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_END = b"IEND\xaeB`\x82"  # the IEND chunk's type and CRC: the last 8 bytes of every complete PNG
JPEG_START, JPEG_END = b"\xff\xd8", b"\xff\xd9"


def _read_bytes(path: Path, what: str) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError as exc:
        raise DatasetError(f"{what} missing: {path}") from exc
    except OSError as exc:
        raise DatasetError(f"cannot read {what} {path}: {exc}") from exc


def decode_rgb(data: bytes, path: str | Path) -> np.ndarray:
    """HxWx3 uint8 in RGB order from a colour file's bytes (OpenCV reads BGR); DatasetError when undecodable or
    truncated. A truncated JPEG decodes "successfully" with a grey lower part (libjpeg only warns), so JPEGs
    must also end with the end-of-image marker."""
    if data[:2] == JPEG_START and JPEG_END not in data[-64:]:
        raise DatasetError(f"truncated JPEG (no end-of-image marker): {path}")
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) if data else None
    if image is None or image.ndim != 3 or image.shape[2] != 3 or image.size == 0:
        raise DatasetError(f"cannot decode colour image (corrupt or not an image): {path}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def decode_depth_u16(data: bytes, path: str | Path, no_reading: int | None = None) -> np.ndarray:
    """HxW uint16 depth from a depth file's bytes as stored (`no_reading`, a dataset's "no reading" marker, set to
    0); DatasetError when undecodable or not 16-bit single channel."""
    depth = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if depth is None or depth.size == 0:
        raise DatasetError(f"cannot decode depth image (corrupt or not an image): {path}")
    if depth.ndim != 2 or depth.dtype != np.uint16:
        raise DatasetError(f"depth image must be single-channel uint16, got {depth.dtype} {depth.shape}: {path}")
    if no_reading is not None:
        depth[depth == no_reading] = 0
    return depth


def read_rgb(path: str | Path) -> np.ndarray:
    """HxWx3 uint8 in RGB order; DatasetError when missing, undecodable or truncated."""
    path = Path(path)
    return decode_rgb(_read_bytes(path, "colour image"), path)


def read_depth_u16(path: str | Path) -> np.ndarray:
    """HxW uint16 depth PNG as stored; DatasetError when missing, undecodable or not 16-bit single channel."""
    path = Path(path)
    return decode_depth_u16(_read_bytes(path, "depth image"), path)


def jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) of a colour JPEG from its frame header (SOFn, baseline or progressive), without decoding
    it, once its headers run whole up to the image data and it ends with the end-of-image marker; None for any
    other file or a damaged one. (The image data itself carries no checksum: libjpeg decodes damage there as
    grey, whoever decodes it.)"""
    if data[:2] != JPEG_START or JPEG_END not in data[-64:]:
        return None
    at, size = 2, None
    while at + 4 <= len(data):
        if data[at] != 0xFF:
            return None
        marker = data[at + 1]
        if marker == 0xFF:  # fill byte
            at += 1
            continue
        length = int.from_bytes(data[at + 2:at + 4], "big")
        if length < 2 or at + 2 + length > len(data):
            return None
        if marker in (0xC0, 0xC1, 0xC2) and length >= 8:
            height = int.from_bytes(data[at + 5:at + 7], "big")
            width = int.from_bytes(data[at + 7:at + 9], "big")
            if not (width and height and data[at + 9] == 3):
                return None
            size = (width, height)
        if marker == 0xDA:  # start of scan: the image data follows
            return size
        at += 2 + length
    return None


def png16_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) of a single-channel 16-bit PNG from its header, without decoding it, once every chunk's
    CRC checks out (~0.05 ms for a 90 KB depth image: a damaged file is caught where it is read, as decoding it
    there would); None for any other file or a damaged one."""
    if data[:8] != PNG_SIGNATURE or data[12:16] != b"IHDR" or not data.endswith(PNG_END) or len(data) < 33:
        return None
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    bit_depth, colour_type = data[24], data[25]
    if not (width and height and bit_depth == 16 and colour_type == 0):
        return None
    at, view = 8, memoryview(data)
    while at + 12 <= len(data):
        length = int.from_bytes(data[at:at + 4], "big")
        end = at + 8 + length
        if end + 4 > len(data) or zlib.crc32(view[at + 4:end]) != int.from_bytes(data[end:end + 4], "big"):
            return None
        if data[at + 4:at + 8] == b"IEND":
            return (width, height) if end + 4 == len(data) else None
        at = end + 4
    return None


def read_rgb_file(path: str | Path) -> EncodedImage:
    """A colour image file, kept encoded: a JPEG whose header and end marker check out is decoded only when its
    pixels are needed (and may travel as is); any other file is decoded now (DatasetError if it cannot be)."""
    path = Path(path)
    data = _read_bytes(path, "colour image")
    size = jpeg_size(data)
    if size is not None:
        return EncodedImage(data, "jpeg", size, lambda: decode_rgb(data, path))
    rgb = decode_rgb(data, path)  # raises on a bad file, as reading always did
    return EncodedImage(data, "other", (rgb.shape[1], rgb.shape[0]), lambda: rgb)


def read_depth_file(path: str | Path) -> EncodedImage:
    """A depth image file, kept encoded: a 16-bit PNG whose header and end chunk check out is decoded only when
    needed (and may travel as is); any other file is decoded now (DatasetError if it cannot be). Either way its
    `DEPTH_NO_READING` (65535, 7-Scenes' marker) reads as 0, as a receiver of the PNG reads it."""
    path = Path(path)
    data = _read_bytes(path, "depth image")
    size = png16_size(data)
    if size is not None:
        return EncodedImage(data, "png16", size, lambda: decode_depth_u16(data, path, DEPTH_NO_READING))
    depth = decode_depth_u16(data, path, DEPTH_NO_READING)
    return EncodedImage(data, "other", (depth.shape[1], depth.shape[0]), lambda: depth)


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image file, decoding it once (used to fill Intrinsics)."""
    image = read_rgb(path)
    return int(image.shape[1]), int(image.shape[0])
