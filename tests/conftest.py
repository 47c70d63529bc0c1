"""Fixtures shared by every test folder."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from semmap.datasets import find_data_root
from semmap.runtime.orchestrator import free_loopback_port
from semmap.runtime.transport.bus import BusConfig

PROJECT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def data_root() -> Path:
    """The shared real-data folder ($SEMMAP_DATA or <project>/../shared/data); skips where it is absent."""
    root = find_data_root()
    if root is None:
        pytest.skip("shared real data absent: set SEMMAP_DATA or provide <project root>/../shared/data")
    return root


@pytest.fixture(scope="session")
def kitchen_dir(data_root: Path) -> Path:
    """The real 7-Scenes redkitchen frames."""
    path = data_root / "7scenes-redkitchen"
    if not path.is_dir():
        pytest.skip(f"no 7scenes-redkitchen/ in {data_root}")
    return path


@pytest.fixture(scope="session")
def bonn_dir(data_root: Path) -> Path:
    """The real Bonn RGB-D Dynamic "crowd" window (people walking; TUM layout)."""
    path = data_root / "bonn_crowd"
    if not (path / "rgb.txt").is_file():
        pytest.skip(f"no bonn_crowd/ in {data_root}")
    return path


class Router:
    """A router-mode Zenoh session in this process (what `eclipse/zenoh` is in compose)."""

    def __init__(self) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
        self.session = zenoh.open(BusConfig(mode="router", listen=[self.endpoint]).to_zenoh())

    def close(self) -> None:
        self.session.close()


@pytest.fixture
def router():
    r = Router()
    yield r
    r.close()


# What makes a test an integration test: it starts processes or opens a bus, a DDS participant or a container
# (a fixture of those, or a module that reaches for them). The rest are unit tests: `pytest -m unit`, in minutes.
INTEGRATION_FIXTURES = {"router", "semmap_run", "kitchen_gt_run", "kitchen_drift_run", "read_stats"}
INTEGRATION_SOURCE = ("subprocess", "zenoh.open", "Bus(", "rclpy", "podman", "multiprocessing", "semmap_run",
                      "service_main", "Router(", "ros_nodes")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark every test `unit` or `integration`, from what it uses: decided here, from the test's fixtures and its
    module's source, so that no test can be left out of both or put in the wrong one by hand."""
    sources: dict[Path, str] = {}
    for item in items:
        path = Path(str(item.fspath))
        if path not in sources:
            sources[path] = path.read_text() if path.is_file() else ""
        fixtures = set(getattr(item, "fixturenames", ()))
        if fixtures & INTEGRATION_FIXTURES or any(word in sources[path] for word in INTEGRATION_SOURCE):
            item.add_marker(pytest.mark.integration)
        else:
            item.add_marker(pytest.mark.unit)


def pytest_runtest_setup(item: pytest.Item) -> None:
    """`needs_data` / `needs_model` tests skip, with the reason, where the data or the model is absent."""
    if item.get_closest_marker("needs_data") and find_data_root() is None:
        pytest.skip("shared real data absent: set SEMMAP_DATA or provide <project root>/../shared/data")
    if item.get_closest_marker("needs_model"):
        from semmap.runtime.models.model_store import default_model_path

        if not default_model_path().is_file():
            pytest.skip("detector model absent: run `semmap models fetch` (./dev.sh does)")


def _semmap_run(args: list[str], timeout: float = 300, env: dict | None = None) -> subprocess.CompletedProcess:
    """`semmap run ...` as a user would type it (its own process), output captured."""
    full_env = {**os.environ, "CI": "true", **(env or {})}
    return subprocess.run([sys.executable, "-m", "semmap.cli", "run", *args, "--quiet"], cwd=PROJECT,
                          capture_output=True, text=True, timeout=timeout, env=full_env)


def _read_stats(out: Path) -> dict:
    return json.loads((out / "stats.json").read_text())


def _run_or_fail(args: list[str], timeout: float = 1500) -> None:
    result = _semmap_run(args, timeout=timeout)
    assert result.returncode == 0, f"semmap run {' '.join(args)}: {result.stderr[-3000:]}"


@pytest.fixture(scope="session")
def kitchen_gt_run(kitchen_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One lockstep `semmap run` of all 1000 7-Scenes frames on ground-truth odometry, no viewer.

    Shared by every test folder that needs it (pipeline, sessions): each such run costs ~2 minutes of CI's 2 cores,
    and the runs are deterministic, so computing it once loses nothing."""
    out = tmp_path_factory.mktemp("kitchen_gt") / "run"
    _run_or_fail([str(kitchen_dir), "--out", str(out), "--odometry", "gt", "--no-viz"])
    return out


@pytest.fixture(scope="session")
def kitchen_drift_run(kitchen_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One lockstep `semmap run` of all 1000 7-Scenes frames on `gt+drift` (seed 1), viewer on (run.rrd written).

    The outputs test and the drift-correction test read the same run (see `kitchen_gt_run` for why)."""
    out = tmp_path_factory.mktemp("kitchen_drift") / "run"
    _run_or_fail([str(kitchen_dir), "--out", str(out), "--odometry", "gt+drift", "--seed", "1", "--lockstep"])
    return out


@pytest.fixture
def semmap_run():
    return _semmap_run


@pytest.fixture
def read_stats():
    return _read_stats
