"""Helpers for tests that run the real pipeline: collectors (`semmap_run` and `read_stats` are in
tests/conftest.py)."""

from __future__ import annotations

import threading
from typing import TypeVar

import pytest

from semmap.core.messages import Message
from semmap.runtime.transport.bus import Bus, BusConfig

M = TypeVar("M", bound=Message)


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


@pytest.fixture
def collector_factory():
    made: list[Collector] = []

    def make(endpoint: str, robot: str, key: str, kind: type[M]) -> Collector:
        made.append(Collector(endpoint, robot, key, kind))
        return made[-1]

    yield make
    for c in made:
        c.close()
