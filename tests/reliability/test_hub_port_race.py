"""Two `semmap run`s starting at the same moment on one machine both find the default port free, and only one can
bind it: the other must host its bus on another free port, not fail (the crash test's clean run, started beside
its run with crashes, failed so). Real sockets and a real Zenoh session; the race is made certain by taking the
port between the check and the bind."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from semmap.runtime import orchestrator
from semmap.runtime.orchestrator import Orchestrator, RunPlan


def test_a_port_taken_between_the_check_and_the_bind_is_not_fatal(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    taken = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    port = taken.getsockname()[1]
    asked: list[int] = []
    free = orchestrator.free_loopback_port

    def racy(preferred: int = 0) -> int:
        """The first answer is a port that another process binds right after the check."""
        asked.append(preferred)
        return port if len(asked) == 1 else free(preferred)

    monkeypatch.setattr(orchestrator, "free_loopback_port", racy)
    orch = Orchestrator(RunPlan("synthetic", tmp_path, "portrace", "lockstep", []))
    try:
        bus, child_args = orch._open_bus()
        bus.close()
    finally:
        taken.close()
    assert len(asked) == 2 and asked[1] == 0
    assert orch.endpoint != f"tcp/127.0.0.1:{port}"
    assert child_args[child_args.index("--connect") + 1] == orch.endpoint
