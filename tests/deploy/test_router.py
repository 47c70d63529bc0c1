"""`python -m semmap.runtime.transport.router`: the router compose runs from semmap's own image (no eclipse/zenoh
there)."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from semmap.core.messages import Control
from semmap.runtime.orchestrator import free_loopback_port
from semmap.runtime.transport.bus import Bus, BusConfig

PROJECT = Path(__file__).resolve().parents[2]


def _assert_routes(endpoint: str) -> None:
    """Two clients that only meet through the router exchange a message."""
    client = BusConfig(mode="client", connect=[endpoint], listen=[])
    a, b = Bus(client, "robot1"), Bus(client, "robot1")
    try:
        got = threading.Event()
        b.subscribe(b.keys.control, Control, lambda c: got.set() if c.command == "stop" else None)
        pub = a.publisher(a.keys.control)
        assert pub.wait_matching(10)
        pub.put(Control("robot1", "stop"))
        assert got.wait(10)
    finally:
        a.close()
        b.close()


def test_router_routes_between_clients_keeps_a_heartbeat_and_stops_on_sigterm(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    health = tmp_path / "health"
    router = subprocess.Popen(
        [sys.executable, "-m", "semmap.runtime.transport.router", "--listen", endpoint, "--health-file", str(health)],
        cwd=PROJECT,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        _assert_routes(endpoint)
        deadline = time.monotonic() + 10
        while not health.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        first = health.stat().st_mtime
        time.sleep(1.5)
        assert health.stat().st_mtime > first, "the heartbeat file is touched while routing"
        router.send_signal(signal.SIGTERM)
        assert router.wait(timeout=15) == 0
    finally:
        if router.poll() is None:
            router.kill()
            router.wait()


def test_router_without_an_endpoint_is_a_usage_error() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "semmap.runtime.transport.router", "--listen", " , "],
        cwd=PROJECT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and "names no endpoint" in result.stderr


def test_the_router_ignores_the_services_connect_variable_and_the_bus_config_can_too(monkeypatch) -> None:  # noqa: ANN001
    """semmap's image sets SEMMAP_ZENOH_CONNECT for its services; the router runs from the same image and must
    not dial it (itself, or a peer that is not up): it routes all the same."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    monkeypatch.setenv("SEMMAP_ZENOH_CONNECT", f"tcp/127.0.0.1:{free_loopback_port()}")
    assert BusConfig.from_env(env_connect=False).connect == []
    assert BusConfig.from_env().connect != []
    router = subprocess.Popen(
        [sys.executable, "-m", "semmap.runtime.transport.router", "--listen", endpoint],
        cwd=PROJECT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        _assert_routes(endpoint)
    finally:
        router.send_signal(signal.SIGTERM)
        try:
            router.wait(timeout=15)
        except subprocess.TimeoutExpired:
            router.kill()
            router.wait()
