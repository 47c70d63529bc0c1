from __future__ import annotations

from pathlib import Path

import pytest

from semmap.core.config import ConfigError, load_config
from semmap.core.keys import InvalidNameError, Keys


def test_keys_are_versioned_and_per_robot() -> None:
    keys = Keys("robot_7")
    assert keys.frames == "semmap/v1/robot_7/frames"
    assert keys.odometry == "semmap/v1/robot_7/odometry"
    assert keys.corrected_poses == "semmap/v1/robot_7/poses/corrected"
    assert keys.status("detector", "detector-2") == "semmap/v1/robot_7/status/detector/detector-2"
    assert keys.progress("tracker") == "semmap/v1/robot_7/progress/tracker"
    assert Keys.instance_of(keys.detector_replica("d1")) == "d1"
    assert Keys("other").frames != keys.frames


@pytest.mark.parametrize("name", ["", "a/b", "*", "**", "x y", "a" * 65, "robot$"])
def test_unsafe_names_are_refused(name: str) -> None:
    with pytest.raises(InvalidNameError):
        Keys(name)


def test_defaults_carry_the_papers_settings() -> None:
    config = load_config()
    assert config.detector.confidence == 0.4
    assert config.detector.depth_min_m == 0.2 and config.detector.depth_max_m == 25.0
    assert (config.tracker.sigma_iou, config.tracker.min_length, config.tracker.max_age_s) == (0.2, 5, 0.5)
    assert config.associator.gate_u == 10.0 and config.associator.refine_every_n_frames == 10


def test_file_and_overrides_layer_on_defaults(tmp_path: Path) -> None:
    user = tmp_path / "my.yaml"
    user.write_text("tracker:\n  sigma_iou: 0.3\nrun:\n  mode: realtime\nassociator:\n  dynamic_classes: [cat]\n")
    config = load_config(user, ["tracker.min_length=7", "detector.classes=[cup, chair]", "associator.absence_p=1e-4"])
    assert config.tracker.sigma_iou == 0.3
    assert config.tracker.min_length == 7
    assert config.run.mode == "realtime"
    assert config.detector.classes == ("cup", "chair")
    assert config.associator.dynamic_classes == ("cat",)
    assert config.associator.absence_p == 1e-4  # (YAML 1.1 would leave "1e-4" a string)
    assert config.tracker.max_age_s == 0.5


@pytest.mark.parametrize("override", ["tracker.sigmaiou=0.1", "nosuch.key=1", "tracker", "=1", "tracker.=1"])
def test_unknown_settings_are_errors(override: str) -> None:
    with pytest.raises(ConfigError):
        load_config(None, [override])


def test_an_unknown_key_names_the_known_ones(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"unknown setting 'tracker.sigmaiou' \(known: sigma_iou, min_length"):
        load_config(None, ["tracker.sigmaiou=0.1"])
    user = tmp_path / "my.yaml"
    user.write_text("trackr:\n  sigma_iou: 0.3\n")
    with pytest.raises(ConfigError, match="unknown setting 'trackr'"):
        load_config(user)


def test_list_syntax() -> None:
    """`a,b` (what a shell gives) and a YAML list are the same list; anything else is refused."""
    for value in ("cup,chair", "[cup, chair]", "cup, chair", "[cup,chair]"):
        assert load_config(None, [f"detector.classes={value}"]).detector.classes == ("cup", "chair")
    assert load_config(None, ["detector.classes=cup"]).detector.classes == ("cup",)
    assert load_config(None, ["detector.classes=[]"]).detector.classes == ()
    assert load_config(None, ["odometry.frame_offset=0,0,0,0,0,90"]).odometry.frame_offset[5] == 90.0
    with pytest.raises(ConfigError, match="detector.classes: expected a list of names"):
        load_config(None, ["detector.classes=[1, 2]"])
    with pytest.raises(ConfigError, match="odometry.frame_offset: expected a list of 6 numbers"):
        load_config(None, ["odometry.frame_offset=[1, 2]"])


# (bad override, key named, expected form): each must be refused by name, none coerced
BAD_VALUES = [
    ("tracker.sigma_iou=banana", "tracker.sigma_iou", "expected a number, got 'banana'"),
    ("tracker.sigma_iou=0", "tracker.sigma_iou", "expected a number > 0"),
    ("detector.confidence=7", "detector.confidence", "expected a number <= 1"),
    ("loop_closure.enabled=maybe", "loop_closure.enabled", "expected true or false, got 'maybe'"),
    ("backend.landmark_constraints=1", "backend.landmark_constraints", "expected true or false, got 1"),
    ("tracker.min_length=1.5", "tracker.min_length", "expected an integer, got 1.5"),
    ("associator.gate_u=0", "associator.gate_u", "expected a number > 0"),
    ("associator.gate_u=1,2", "associator.gate_u", "expected a number"),
    ("associator.dynamic_classes={a: 1}", "associator.dynamic_classes", "expected a list of names"),
    ("detector.model=/no/such/model.onnx", "detector.model", "expected an existing file"),
    ("detector.kind=", "detector.kind", "expected text"),
    ("run.robot=a/b", "run.robot", "invalid robot name 'a/b'"),
    ("run.mode=fast", "run.mode", "expected 'lockstep' or 'realtime'"),
    ("run.deadline_s=.nan", "run.deadline_s", "expected a finite number"),
    ("backend.robust_kernel=tukey", "backend.robust_kernel", "expected 'huber', 'cauchy' or 'none'"),
    ("loop_closure.depth_min_m=9", "loop_closure", "depth_min_m must be below depth_max_m"),
    ("rosbag.topics=[a]", "rosbag.topics", "expected text"),
    ("associator.prior_anchor_sigma_m=-1", "associator.prior_anchor_sigma_m", "expected a number > 0"),
]


@pytest.mark.parametrize(("override", "key", "expected"), BAD_VALUES)
def test_bad_values_name_the_key_and_the_expected_form(override: str, key: str, expected: str) -> None:
    with pytest.raises(ConfigError) as err:
        load_config(None, [override])
    assert str(err.value).startswith(f"{key}: {expected}"), str(err.value)


def test_every_bad_key_is_reported_at_once() -> None:
    with pytest.raises(ConfigError) as err:
        load_config(None, ["tracker.sigma_iou=banana", "detector.confidence=7"])
    assert "tracker.sigma_iou" in str(err.value) and "detector.confidence" in str(err.value)


def test_the_sections_are_the_algorithms_parameters() -> None:
    """One definition: what the algorithms take is the section itself (no second copy of the defaults)."""
    from semmap.algorithms.associator.params import MapperParams
    from semmap.algorithms.backend.loop_closure import LoopClosureParams
    from semmap.algorithms.backend.pose_graph import BackendParams
    from semmap.algorithms.tracker.iou_tracker import TrackerParams

    config = load_config()
    assert isinstance(config.associator, MapperParams) and isinstance(config.tracker, TrackerParams)
    assert isinstance(config.backend, BackendParams) and isinstance(config.loop_closure, LoopClosureParams)
    assert config.associator.prior().anchor_sigma_m == 0.03


def test_the_printed_configuration_loads_back(tmp_path: Path) -> None:
    from semmap.core.config import render_yaml

    config = load_config(None, ["detector.classes=cup,chair", "tracker.sigma_iou=0.3"])
    text = render_yaml(config)
    assert "  sigma_iou: 0.3" in text and "  classes: [cup, chair]" in text
    assert "# paper" in text  # descriptions as comments
    (tmp_path / "shown.yaml").write_text(text)
    assert load_config(tmp_path / "shown.yaml") == config


def test_unreadable_config_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("tracker: [1, 2\n")
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(bad)
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(tmp_path / "missing.yaml")
    bad.write_text("- tracker\n")
    with pytest.raises(ConfigError, match="must be a mapping of sections"):
        load_config(bad)
