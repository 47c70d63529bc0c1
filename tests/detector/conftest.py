"""Fixtures for the detector tests: the fetched model and a shared detector instance (7-Scenes frames come from
tests/conftest.py's `kitchen_dir`)."""

from __future__ import annotations

from pathlib import Path

import pytest

from semmap.runtime.models.model_store import default_model_path

FETCH_REASON = "detector model absent: run `semmap models fetch`"


@pytest.fixture(scope="session")
def model_path() -> Path:
    path = default_model_path()
    if not path.is_file():
        pytest.skip(FETCH_REASON)
    return path


@pytest.fixture(scope="session")
def yolo(model_path: Path):
    from semmap.algorithms.detector.onnx_detector import OnnxDetector

    return OnnxDetector(model_path, conf=0.4, iou=0.45, threads=2)
