"""Tracker + mapper end to end, no bus: the synthetic scene with the oracle detector, and real 7-Scenes frames
with the ONNX detector, both with ground-truth poses.

Synthetic criteria: every static object mapped exactly once (recall >= 95 %, no duplicates), median centroid
error <= 5 cm against `dataset.objects()`, and no landmark on a person *while it was walking*: a person that
stood nearly still (< 0.35 m from its mean position) through every view of a landmark is, as far as the data
shows, a static object, and no class-agnostic mapper (the paper's included) can tell otherwise.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from semmap.algorithms.associator.mapper import MapperParams
from semmap.algorithms.detector.oracle import OracleDetector
from semmap.datasets.synthetic import SyntheticConfig, SyntheticDataset
from semmap.runtime.pipeline.inprocess import OfflineRun, run_offline, score_map


def synthetic_run(width: int, height: int, every: int, seed: int = 0,
                  params: MapperParams | None = None) -> tuple[SyntheticDataset, OfflineRun]:
    ds = SyntheticDataset(SyntheticConfig(frames=300, width=width, height=height, seed=seed))
    # The oracle's visibility floor (300 px at 640x480) scales with the image area.
    oracle = OracleDetector(seed=seed, min_visible_pixels=int(300 * width * height / (640 * 480)))
    frames = (ds[i] for i in range(0, len(ds), every))
    poses = {i: ds.camera_pose(i) for i in range(len(ds))}
    run = run_offline(frames, lambda f: oracle.detect(f.index, f.instances, width, height), poses,
                      mapper_params=params)
    return ds, run


def person_moved_m(ds: SyntheticDataset, run: OfflineRun) -> list[float]:
    """For each person landmark: how far the nearest walking person strayed from its mean position over the
    frames of the landmark's views."""
    out = []
    moving = [o.instance_id for o in ds.objects() if o.moving]
    for lm in run.mapper.map.all():
        if lm.class_name != "person":
            continue
        frames = sorted({v.frame_id for v in lm.views})
        paths = {i: np.array([ds.object_centroids(f)[i] for f in frames]) for i in moving}
        near = min(moving, key=lambda i: float(np.min(np.linalg.norm(paths[i] - lm.centroid, axis=1))))
        path = paths[near]
        out.append(float(np.max(np.linalg.norm(path - path.mean(axis=0), axis=1))))
    return out


def check_synthetic(ds: SyntheticDataset, run: OfflineRun) -> None:
    score = score_map(run.mapper.landmarks(), ds.objects())
    assert score.recall >= 0.95, score
    assert score.duplicates == 0, score
    assert score.median_error <= 0.05, score
    moved = person_moved_m(ds, run)
    assert all(m < 0.35 for m in moved), moved
    assert score.false_landmarks == len(moved), score  # nothing else unmatched
    assert sum(len(s.rejected) for s in run.steps) >= 1  # the walking people were seen and rejected


@pytest.mark.parametrize("prior", [True, False], ids=["class-prior", "geometry-only"])
def test_synthetic_scene_every_second_frame(prior: bool) -> None:
    """300-frame loop at 320x240, detected every second frame (15 Hz); people kept out by their class (the
    default) or by the motion tests alone (`associator.dynamic_classes` emptied)."""
    ds, run = synthetic_run(320, 240, every=2, params=None if prior else MapperParams(dynamic_classes=()))
    if prior:
        score = score_map(run.mapper.landmarks(), ds.objects())
        assert score.recall >= 0.95 and score.duplicates == 0 and score.median_error <= 0.05, score
        assert score.false_landmarks == 0 and all(lm.class_name != "person" for lm in run.mapper.landmarks())
    else:
        check_synthetic(ds, run)


@pytest.mark.slow
def test_synthetic_scene_every_frame_vga() -> None:
    """The full 300-frame loop at 640x480, every frame detected; the walking people kept out by the motion tests
    alone (the class prior would keep them from ever being candidates)."""
    ds, run = synthetic_run(640, 480, every=1, params=MapperParams(dynamic_classes=()))
    check_synthetic(ds, run)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_synthetic_scene_other_seeds(seed: int) -> None:
    ds, run = synthetic_run(320, 240, every=2, seed=seed)
    score = score_map(run.mapper.landmarks(), ds.objects())
    assert score.recall >= 0.95 and score.duplicates == 0, score
    assert score.median_error <= 0.06, score
    assert all(m < 0.35 for m in person_moved_m(ds, run))


# ---------------------------------------------------------------------------------------------------------
# real frames


@pytest.fixture(scope="module")
def yolo_7scenes(data_root: Path):
    from semmap.algorithms.detector.onnx_detector import OnnxDetector
    from semmap.runtime.models.model_store import default_model_path

    folder = data_root / "7scenes-redkitchen"
    if not folder.is_dir():
        pytest.skip(f"7-Scenes frames absent under {data_root}")
    model = default_model_path()
    if not model.is_file():
        pytest.skip("detector model absent: run `semmap models fetch`")
    from semmap.datasets.sevenscenes import SevenScenesDataset

    return SevenScenesDataset(folder), OnnxDetector(model, conf=0.4, threads=2)


def min_same_class_distance(landmarks: list) -> float:
    best = float("inf")
    for i, a in enumerate(landmarks):
        for b in landmarks[i + 1 :]:
            if a.class_name == b.class_name:
                best = min(best, float(np.linalg.norm(np.subtract(a.centroid, b.centroid))))
    return best


def sevenscenes_run(ds, detector, n: int, every: int) -> OfflineRun:  # noqa: ANN001
    frames = [ds[i] for i in range(0, n, every)]
    poses = {f.index: f.gt_pose for f in frames}
    return run_offline(frames, lambda f: detector.detect(f.rgb), poses)


@pytest.mark.needs_data
@pytest.mark.needs_model
def test_7scenes_no_duplicate_landmarks(yolo_7scenes) -> None:  # noqa: ANN001
    """Every 3rd of the first 300 frames (10 Hz) with the real detector: no two same-class landmarks closer
    than 0.25 m (the handbook's greedy baseline made duplicates of chairs, tables, screens)."""
    ds, detector = yolo_7scenes
    run = sevenscenes_run(ds, detector, 300, 3)
    landmarks = run.mapper.landmarks()
    assert len(landmarks) >= 5
    assert {"chair", "cup"} <= {lm.class_name for lm in landmarks}
    assert min_same_class_distance(landmarks) > 0.25


@pytest.mark.slow
@pytest.mark.needs_data
@pytest.mark.needs_model
def test_7scenes_full_sequence(yolo_7scenes) -> None:  # noqa: ANN001
    """All 1000 frames, every 3rd: the camera walks round the table and comes back (revisits)."""
    ds, detector = yolo_7scenes
    run = sevenscenes_run(ds, detector, len(ds), 3)
    landmarks = run.mapper.landmarks()
    assert min_same_class_distance(landmarks) > 0.25
    assert len(landmarks) <= 22  # a simple greedy map made 26-27 (handbook)
