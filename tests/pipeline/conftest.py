"""Helpers for tests that run the real pipeline: processes, a Zenoh router, collectors."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import TypeVar

import pytest

from semmap.bus import Bus, BusConfig
from semmap.messages import Message

M = TypeVar("M", bound=Message)
PROJECT = Path(__file__).resolve().parents[2]


class Collector:
    """Subscribes to one key through the router and keeps every valid message."""

    def __init__(self, endpoint: str, robot: str, key: str, kind: type[M]) -> None:
        self.bus = Bus(BusConfig(mode="client", connect=[endpoint], listen=[]), robot)
        self.items: list[M] = []
        self._lock = threading.Lock()
        self.bus.subscribe(key.format(root=self.bus.keys.root), kind, self._add)

    def _add(self, message: M) -> None:
        with self._lock:
            self.items.append(message)

    def close(self) -> None:
        if not self.bus.session.is_closed():
            self.bus.close()


def _semmap_run(args: list[str], timeout: float = 300, env: dict | None = None) -> subprocess.CompletedProcess:
    """`semmap run ...` as a user would type it (its own process), output captured."""
    full_env = {**os.environ, "CI": "true", **(env or {})}
    return subprocess.run([sys.executable, "-m", "semmap.cli", "run", *args, "--quiet"], cwd=PROJECT,
                          capture_output=True, text=True, timeout=timeout, env=full_env)


def _read_stats(out: Path) -> dict:
    return json.loads((out / "stats.json").read_text())


@pytest.fixture
def semmap_run():
    return _semmap_run


@pytest.fixture
def read_stats():
    return _read_stats


@pytest.fixture
def collector_factory():
    made: list[Collector] = []

    def make(endpoint: str, robot: str, key: str, kind: type[M]) -> Collector:
        made.append(Collector(endpoint, robot, key, kind))
        return made[-1]

    yield make
    for c in made:
        c.close()
