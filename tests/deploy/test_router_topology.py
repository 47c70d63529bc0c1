"""The compose topology without Docker: a router-mode Zenoh process, every service a client of it, two detector
replicas. The map equals the embedded (peer-to-peer) run's."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from semmap.runtime.orchestrator import free_loopback_port

PROJECT = Path(__file__).resolve().parents[2]
DATA = "synthetic:frames=60"


def _run(args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "semmap.cli", "run", DATA, "--quiet", "--no-viz", "--odometry",
                           "gt+drift", *args], cwd=PROJECT, capture_output=True, text=True, timeout=400,
                          env={**os.environ, "CI": "true"})


def test_router_with_client_services_and_two_detectors_maps_like_the_embedded_run(tmp_path: Path) -> None:
    embedded = tmp_path / "embedded"
    result = _run(["--out", str(embedded)])
    assert result.returncode == 0, result.stderr[-3000:]

    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    router = subprocess.Popen(
        [sys.executable, "-c", "import sys, time, zenoh\n"
         "from semmap.runtime.transport.bus import BusConfig\n"
         f"s = zenoh.open(BusConfig(mode='router', listen=['{endpoint}']).to_zenoh())\n"
         "print('up', flush=True)\n"
         "time.sleep(600)\n"], cwd=PROJECT, stdout=subprocess.PIPE, text=True)
    try:
        assert router.stdout is not None and router.stdout.readline().strip() == "up"
        routed = tmp_path / "routed"
        started = time.monotonic()
        result = _run(["--out", str(routed), "--connect", endpoint, "--zenoh-mode", "client", "--detectors", "2"])
        assert result.returncode == 0, result.stderr[-3000:]
        assert time.monotonic() - started < 400
    finally:
        router.kill()
        router.wait()
    stats = json.loads((routed / "stats.json").read_text())
    detectors = [s for s in stats["services"].values() if s["service"] == "detector"]
    assert len(detectors) == 2 and all(s["counters"].get("frames_detected", 0) > 10 for s in detectors)
    assert json.loads((routed / "map.json").read_text()) == json.loads((embedded / "map.json").read_text())
    assert (routed / "trajectory_optimized.tum").read_text() == (embedded / "trajectory_optimized.tum").read_text()
