"""Fixtures for the detector tests: the 7-Scenes frames, the fetched model, a shared detector instance."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from services.detector.model_store import default_model_path

FETCH_REASON = "detector model absent: run `semmap models fetch`"


def read_rgb(path: Path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert bgr is not None, f"cannot read {path}"
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)  # OpenCV decodes to BGR; the detector takes RGB


@pytest.fixture(scope="session")
def shared_data(data_root: Path) -> Path:
    """The shared data root (tests/conftest.py's `data_root`), with the 7-Scenes frames in it."""
    if not (data_root / "7scenes-redkitchen").is_dir():
        pytest.skip(f"7-Scenes frames absent under {data_root}")
    return data_root


@pytest.fixture(scope="session")
def model_path() -> Path:
    path = default_model_path()
    if not path.is_file():
        pytest.skip(FETCH_REASON)
    return path


@pytest.fixture(scope="session")
def yolo(model_path: Path):
    from services.detector.onnx_detector import OnnxDetector

    return OnnxDetector(model_path, conf=0.4, iou=0.45, threads=2)
