"""Services start in any order, and the run survives the Zenoh router going away and coming back."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from semmap.core.messages import Control
from semmap.runtime.orchestrator import free_loopback_port
from semmap.runtime.transport.bus import Bus, BusConfig

PROJECT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "CI": "true"}


def _router(endpoint: str) -> subprocess.Popen:
    proc = subprocess.Popen(
        [sys.executable, "-c", "import time, zenoh\nfrom semmap.runtime.transport.bus import BusConfig\n"
         f"s = zenoh.open(BusConfig(mode='router', listen=['{endpoint}']).to_zenoh())\n"
         "print('up', flush=True)\ntime.sleep(3600)\n"], cwd=PROJECT, stdout=subprocess.PIPE, text=True, env=ENV)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "up"
    return proc


def _service(name: str, endpoint: str, out: Path, *extra: str) -> subprocess.Popen:
    log = open(out / f"{name}.log", "wb")  # noqa: SIM115 - closed with the process
    module = f"semmap.services.{name}"
    return subprocess.Popen([sys.executable, "-m", module, "--connect", endpoint, "--zenoh-mode", "client",
                             "--robot", "order", "--out", str(out), "--set", "odometry.mode=gt", *extra],
                            cwd=PROJECT, stdout=log, stderr=subprocess.STDOUT, env=ENV)


def test_reverse_start_order_and_a_router_restart(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    router = _router(endpoint)
    procs: list[subprocess.Popen] = []
    try:
        # the player first, the odometry last: the player waits until everyone it needs is up
        procs.append(_service("player", endpoint, tmp_path, "--data", "synthetic:frames=120",
                              "--wait-for", "odometry,detector,tracker"))
        time.sleep(2)
        procs.append(_service("tracker", endpoint, tmp_path))
        procs.append(_service("detector", endpoint, tmp_path, "--set", "detector.kind=oracle"))
        time.sleep(1)
        procs.append(_service("odometry", endpoint, tmp_path))
        deadline = time.monotonic() + 120
        odometry_log = tmp_path / "trajectory_odometry.tum"
        while "pipeline ready" not in (tmp_path / "player.log").read_text() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert "pipeline ready" in (tmp_path / "player.log").read_text(), "the pipeline never came up"
        time.sleep(3)  # some frames through
        assert "end of stream after" not in (tmp_path / "player.log").read_text(), \
            "the stream ended before the router restart: the test proved nothing"
        router.kill()
        router.wait()
        time.sleep(2)
        router = _router(endpoint)  # same endpoint: clients reconnect by themselves
        deadline = time.monotonic() + 240
        while "end of stream after" not in (tmp_path / "player.log").read_text() and time.monotonic() < deadline:
            assert procs[0].poll() is None, (tmp_path / "player.log").read_text()[-3000:]
            time.sleep(0.5)
        # every service finished the stream and stops on request
        bus = Bus(BusConfig(mode="client", connect=[endpoint], listen=[]), "order")
        control = bus.publisher(bus.keys.control)
        control.wait_matching(10)
        control.put(Control("order", "stop"))
        for proc in procs:
            name = proc.args[2].rsplit(".", 1)[-1]  # `-m semmap.services.<name>`: its log is <name>.log
            code = proc.wait(timeout=30)
            assert code == 0, f"{name} exited with {code}:\n" + (tmp_path / f"{name}.log").read_text()[-3000:]
        bus.close()
        lines = [ln for ln in odometry_log.read_text().splitlines() if not ln.startswith("#")]
        assert len(lines) == 120
        player_log = (tmp_path / "player.log").read_text()
        assert "end of stream after 120 frames" in player_log
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
        router.kill()
