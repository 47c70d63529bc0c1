"""Settings one way in: environment variables are read in one module that lists them, the `--mode` / `--robot`
flags are validated settings, and a run hands its children one effective configuration file."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from semmap.core import environment
from semmap.core.config import ConfigError, load_config, render_yaml, run_overrides

PROJECT = Path(__file__).resolve().parents[2]
SOURCES = sorted((PROJECT / "semmap").rglob("*.py"))


def test_the_environment_is_read_in_one_place() -> None:
    """No module but semmap/core/environment.py reads a variable (`os.environ.get`, `os.environ[...]`, `getenv`,
    `setdefault`); handing a child the whole environment (`{**os.environ, ...}`) is not a read."""
    reads = re.compile(r"os\.environ\.get|os\.environ\[|os\.getenv|os\.environ\.setdefault")
    offenders = [f"{p.relative_to(PROJECT)}:{i}" for p in SOURCES if p.name != "environment.py"
                 for i, line in enumerate(p.read_text().splitlines(), 1) if reads.search(line)]
    assert not offenders, offenders


def test_every_semmap_variable_is_listed_with_its_meaning() -> None:
    named = {m for p in SOURCES for m in re.findall(r"\bSEMMAP_[A-Z_]*[A-Z]\b", p.read_text())}
    assert named <= set(environment.BY_NAME), named - set(environment.BY_NAME)
    assert all(v.meaning for v in environment.VARIABLES)
    with pytest.raises(KeyError, match="not a listed"):
        environment.read("SEMMAP_UNHEARD_OF")


def test_mode_and_robot_are_validated_settings() -> None:
    config = load_config(None, run_overrides("realtime", "007"))
    assert config.run.mode == "realtime" and config.run.robot == "007"  # (digits stay a name)
    with pytest.raises(ConfigError, match="run.mode"):
        load_config(None, run_overrides("sometimes", None))
    with pytest.raises(ConfigError, match="run.robot"):
        load_config(None, run_overrides(None, "a/b"))
    assert run_overrides(None, None) == []


def test_the_run_writes_the_effective_configuration_its_children_read(tmp_path: Path) -> None:
    from semmap.runtime.orchestrator import SETTINGS_FILE, Orchestrator, RunPlan

    plan = RunPlan("synthetic", tmp_path, "robot7", "realtime", [], overrides=["tracker.sigma_iou=0.3"])
    path = Orchestrator(plan).write_settings()
    assert path == tmp_path / SETTINGS_FILE
    config = load_config(path)
    assert config.run.robot == "robot7" and config.run.mode == "realtime" and config.tracker.sigma_iou == 0.3
    assert path.read_text() == render_yaml(config)
