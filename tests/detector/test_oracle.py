"""OracleDetector: seeded determinism independent of call order, and noise rates that match the settings."""

from __future__ import annotations

import random

import numpy as np
import pytest

from semmap.algorithms.detector.oracle import COCO_NAMES, OracleDetector
from semmap.datasets.base import InstanceBox

W, H = 640, 480


def _grid_instances(n: int = 12) -> list[InstanceBox]:
    """Well separated boxes, so every detection can be matched to its instance by position."""
    out = []
    for i in range(n):
        x, y = 20 + (i % 4) * 155, 20 + (i // 4) * 150
        out.append(InstanceBox(i, ("chair", "cup", "tv")[i % 3], (x, y, x + 100, y + 90), 5000))
    return out


def _match(dets, instances, tol=12.0):
    """(matched pairs, unmatched detections)."""
    pairs, spurious = [], []
    for d in dets:
        best = [inst for inst in instances if np.abs(np.subtract((d.x1, d.y1, d.x2, d.y2), inst.box)).max() < tol]
        (pairs.append((d, best[0])) if best else spurious.append(d))
    return pairs, spurious


def test_deterministic_regardless_of_call_order_and_instance_order():
    inst = _grid_instances()
    a = OracleDetector(seed=7)
    forward = {f: a.detect(f, inst, W, H) for f in range(30)}
    b = OracleDetector(seed=7)
    shuffled = list(inst)
    random.Random(0).shuffle(shuffled)
    for f in reversed(range(30)):
        assert b.detect(f, shuffled, W, H) == forward[f]
    assert OracleDetector(seed=8).detect(3, inst, W, H) != forward[3]


def test_noise_rates_match_settings():
    inst = _grid_instances()
    oracle = OracleDetector(seed=1, miss_rate=0.05, false_positive_rate=0.02, confusion_rate=0.02, box_noise_px=2.0)
    frames = 1500
    detected = confused = spurious = 0
    errors = []
    for f in range(frames):
        pairs, extra = _match(oracle.detect(f, inst, W, H), inst)
        detected += len(pairs)
        confused += sum(d.class_name != i.class_name for d, i in pairs)
        spurious += len(extra)
        errors.extend(np.subtract((d.x1, d.y1, d.x2, d.y2), i.box) for d, i in pairs)
        assert all(0.5 <= d.score <= 0.95 for d, _ in pairs)
    total = frames * len(inst)
    assert 1 - detected / total == pytest.approx(0.05, abs=0.008)
    assert confused / detected == pytest.approx(0.02, abs=0.005)
    assert spurious / frames == pytest.approx(0.02, abs=0.012)
    assert np.std(errors) == pytest.approx(2.0, rel=0.05)
    assert abs(np.mean(errors)) < 0.1


def test_noiseless_oracle_is_exact_and_sorted():
    inst = _grid_instances()
    oracle = OracleDetector(seed=0, miss_rate=0, false_positive_rate=0, confusion_rate=0, box_noise_px=0)
    dets = oracle.detect(5, inst, W, H)
    assert sorted((d.x1, d.y1, d.x2, d.y2) for d in dets) == sorted(i.box for i in inst)
    assert [d.score for d in dets] == sorted((d.score for d in dets), reverse=True)
    assert {d.class_id for d in dets} == {COCO_NAMES.index(n) for n in ("chair", "cup", "tv")}


def test_small_instances_are_never_detected_and_boxes_stay_in_the_image():
    tiny = InstanceBox(1, "cup", (100, 100, 110, 110), 299)
    edge = InstanceBox(2, "chair", (0, 0, 200, 480), 20000)
    oracle = OracleDetector(seed=3, miss_rate=0, false_positive_rate=0, box_noise_px=5.0)
    for f in range(50):
        dets = oracle.detect(f, [tiny, edge], W, H)
        assert len(dets) == 1
        d = dets[0]
        assert 0 <= d.x1 < d.x2 <= W and 0 <= d.y1 < d.y2 <= H


def test_unknown_class_gets_id_minus_one():
    dets = OracleDetector(seed=0, miss_rate=0, confusion_rate=0).detect(
        0, [InstanceBox(1, "robot", (10, 10, 90, 90), 5000)], W, H
    )
    assert dets[0].class_name == "robot" and dets[0].class_id == -1


@pytest.mark.parametrize(
    "kwargs", [{"miss_rate": 1.5}, {"confusion_rate": -0.1}, {"false_positive_rate": -1}, {"seed": -1}]
)
def test_bad_settings(kwargs):
    with pytest.raises(ValueError):
        OracleDetector(**{"seed": 0, **kwargs})
