"""The OpenCV image codec frames use by default (`semmap.core.messages.frames.image_codec`): JPEG for colour,
16-bit PNG for depth.

A leaf module on purpose (numpy and OpenCV, nothing of semmap): core finds it by name the first time a frame's
pixels are needed, so core itself never imports OpenCV, and the light client ships it beside the messages.
"""

from __future__ import annotations

import cv2
import numpy as np


class OpenCVImageCodec:
    """`semmap.core.messages.ImageCodec` on OpenCV; every method returns None where OpenCV fails."""

    def encode_jpeg(self, rgb: np.ndarray, quality: int) -> bytes | None:
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
        return buf.tobytes() if ok else None

    def decode_jpeg(self, data: bytes) -> np.ndarray | None:
        try:
            bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        except cv2.error:
            return None
        return None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def encode_png16(self, image: np.ndarray) -> bytes | None:
        ok, png = cv2.imencode(".png", image)
        return png.tobytes() if ok else None

    def decode_png16(self, data: bytes) -> np.ndarray | None:
        try:
            return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        except cv2.error:
            return None
