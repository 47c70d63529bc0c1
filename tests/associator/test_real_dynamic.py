"""Real walking people (Bonn RGB-D Dynamic "crowd", the camera following them) never become landmarks: by their
class, and by geometry alone (`associator.dynamic_classes` emptied), while the office chairs still map."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest

from semmap.algorithms.associator.mapper import MapperParams
from semmap.datasets.tum import TumDataset
from semmap.runtime.pipeline.inprocess import OfflineRun, run_offline

WINDOW = range(285, 400)  # two people near the camera (one 1.7 s, truncated by the image border) and two chairs


@pytest.fixture(scope="module")
def crowd(data_root: Path) -> tuple[TumDataset, dict]:
    path = data_root / "bonn_crowd"
    if not (path / "rgb.txt").is_file():
        pytest.skip("bonn_crowd absent from the shared data")
    from semmap.algorithms.detector.onnx_detector import OnnxDetector
    from semmap.runtime.models.model_store import default_model_path

    ds = TumDataset(path)
    detector = OnnxDetector(default_model_path(), conf=0.4, iou=0.45, threads=2)
    return ds, {i: detector.detect(ds[i].rgb) for i in WINDOW}


def _run(crowd: tuple[TumDataset, dict], params: MapperParams) -> OfflineRun:
    ds, boxes = crowd
    poses = {i: ds[i].gt_pose for i in WINDOW}
    return run_offline((ds[i] for i in WINDOW), lambda f: boxes[f.index], poses, mapper_params=params)


@pytest.mark.slow  # (115 frames of ONNX detection)
@pytest.mark.needs_model
@pytest.mark.parametrize("prior", [True, False], ids=["class-prior", "geometry-only"])
def test_real_walking_people_never_become_landmarks(crowd, prior: bool) -> None:
    params = MapperParams() if prior else MapperParams(dynamic_classes=())
    run = _run(crowd, params)
    classes = Counter(lm.class_name for lm in run.mapper.landmarks())
    assert classes["person"] == 0, classes
    assert classes["chair"] >= 1, classes  # the static office furniture still maps
    if not prior:  # the people were candidates and geometry turned them down as moving
        assert any(s.moving_tracks for s in run.steps)
