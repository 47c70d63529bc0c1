"""Detector back ends and odometry front ends are picked from registries (like datasets), `auto` decided once."""

from __future__ import annotations

import numpy as np
import pytest

from semmap.algorithms import detector, odometry
from semmap.algorithms.odometry.frontends import DriftingOdometry, FileOdometry, FrontEnd, OdometryInput
from semmap.core.config import ConfigError, DetectorConfig, OdometryConfig, load_config
from semmap.core.messages import Frame


def test_the_detector_back_ends_are_registered_and_auto_is_decided_in_one_place() -> None:
    assert set(detector.available()) >= {"onnx", "oracle"}
    assert detector.resolve_kind("auto", synthetic=True) == "oracle"
    assert detector.resolve_kind("auto", synthetic=False) == "onnx"
    assert detector.resolve_kind("oracle", synthetic=False) == "oracle"
    assert detector.needs_model("onnx") and not detector.needs_model("oracle")
    with pytest.raises(ConfigError, match="detector.kind: expected one of auto, oracle, onnx"):
        detector.resolve_kind("yolo", synthetic=False)


def test_the_oracle_back_end_detects_a_synthetic_frame_with_the_sections_lists() -> None:
    from semmap.datasets import open_dataset
    from semmap.services.player.service import frame_message

    frame = frame_message("r", open_dataset("synthetic:frames=3")[1])
    everything = detector.create_detector(
        "oracle", DetectorConfig(oracle_miss_rate=0.0, oracle_false_positive_rate=0.0)
    )
    boxes = everything.detect_frame(frame)
    assert boxes, "the synthetic scene shows objects"
    first = boxes[0].class_name
    only = detector.create_detector(
        "oracle", DetectorConfig(classes=[first], oracle_miss_rate=0.0, oracle_false_positive_rate=0.0)
    )
    assert {b.class_name for b in only.detect_frame(frame)} == {first}
    without = detector.create_detector(
        "oracle", DetectorConfig(exclude=[first], oracle_miss_rate=0.0, oracle_false_positive_rate=0.0)
    )
    assert first not in {b.class_name for b in without.detect_frame(frame)}


def test_a_new_detector_back_end_joins_by_registering() -> None:
    class Nothing:
        def detect_frame(self, frame: Frame) -> list:
            return []

    detector.register("nothing", lambda section, model: Nothing(), "detects nothing (a test)")
    try:
        assert detector.resolve_kind("nothing", synthetic=False) == "nothing"
        assert detector.create_detector("nothing", DetectorConfig(kind="nothing")).detect_frame(None) == []
    finally:
        detector._REGISTRY.pop("nothing")


def test_the_odometry_front_ends_are_registered(tmp_path) -> None:  # noqa: ANN001
    assert set(odometry.available()) == {"auto", "orbslam3", "gt", "gt+drift", "rgbd", "file:PATH", "external"}
    section = load_config(None, ["odometry.seed=4", "odometry.repair=false"]).odometry
    drift = odometry.create_frontend("gt+drift", section)
    assert isinstance(drift, DriftingOdometry) and odometry.check_mode("gt+drift")[0].needs_groundtruth
    (tmp_path / "t.tum").write_text("0.0 1 2 3 0 0 0 1\n")
    front = odometry.create_frontend(f"file:{tmp_path / 't.tum'}", section)
    assert isinstance(front, FileOdometry) and not odometry.check_mode("file:x")[0].needs_groundtruth
    assert front.estimate(OdometryInput(0, 0.0, None))[0, 3] == 1.0


def test_a_new_front_end_joins_by_registering() -> None:
    class Still(FrontEnd):
        sigmas = (0.1, 0.1)

        def estimate(self, frame: OdometryInput) -> np.ndarray:
            return np.eye(4)

    odometry.register("still", lambda section, arg: Still(), "never moves (a test)")
    try:
        assert isinstance(odometry.create_frontend("still", OdometryConfig(mode="still")), Still)
    finally:
        odometry._REGISTRY.pop("still")
