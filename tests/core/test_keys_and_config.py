from __future__ import annotations

from pathlib import Path

import pytest

from semmap.config import ConfigError, load_config
from semmap.keys import InvalidNameError, Keys


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
    assert config["detector"]["confidence"] == 0.4
    assert config["detector"]["depth_min_m"] == 0.2 and config["detector"]["depth_max_m"] == 25.0
    assert {k: config["tracker"][k] for k in ("sigma_iou", "min_length", "max_age_s")} == {
        "sigma_iou": 0.2, "min_length": 5, "max_age_s": 0.5}


def test_file_and_overrides_layer_on_defaults(tmp_path: Path) -> None:
    user = tmp_path / "my.yaml"
    user.write_text("tracker:\n  sigma_iou: 0.3\nrun:\n  mode: realtime\n")
    config = load_config(user, ["tracker.min_length=7", "detector.classes=[cup, chair]"])
    assert config["tracker"]["sigma_iou"] == 0.3
    assert config["tracker"]["min_length"] == 7
    assert config["run"]["mode"] == "realtime"
    assert config["detector"]["classes"] == ["cup", "chair"]
    assert config["tracker"]["max_age_s"] == 0.5


@pytest.mark.parametrize("override", ["tracker.sigmaiou=0.1", "nosuch.key=1", "tracker", "=1"])
def test_unknown_settings_are_errors(override: str) -> None:
    with pytest.raises(ConfigError):
        load_config(None, [override])


def test_unreadable_config_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("tracker: [1, 2\n")
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(bad)
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(tmp_path / "missing.yaml")
