"""Real Zenoh sessions between real processes: the odometry service answers frames published from here."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from semmap.core.messages import Control, Frame, Intrinsics, OdometryPose, ServiceStatus
from semmap.runtime.orchestrator import free_loopback_port
from semmap.runtime.transport.bus import Bus, BusConfig, Inbox

K = Intrinsics(500.0, 500.0, 16.0, 12.0, 32, 24)


def test_inbox_drops_oldest_per_stream_and_counts() -> None:
    inbox = Inbox()
    inbox.add_stream("frames", 2)
    inbox.add_stream("control", 10)
    for i in range(5):
        inbox.put("frames", i)
    inbox.put("control", "stop")
    got = [inbox.get(0.01) for _ in range(3)]
    assert got == [("frames", 3), ("frames", 4), ("control", "stop")]
    assert inbox.dropped["frames"] == 3 and inbox.dropped["control"] == 0
    assert inbox.get(0.01) is None


def test_bus_config_from_flags_and_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SEMMAP_ZENOH_CONNECT", "tcp/10.0.0.1:7447")
    monkeypatch.setenv("SEMMAP_ZENOH_MODE", "client")
    cfg = BusConfig.from_env()
    assert cfg.mode == "client" and cfg.connect == ["tcp/10.0.0.1:7447"] and cfg.listen == []
    cfg = BusConfig.from_env(connect="tcp/127.0.0.1:1", mode="peer")
    assert cfg.mode == "peer" and cfg.connect == ["tcp/127.0.0.1:1"] and cfg.listen == ["tcp/127.0.0.1:0"]
    assert not cfg.multicast_scouting
    monkeypatch.setenv("SEMMAP_ZENOH_MODE", "mesh")
    with pytest.raises(Exception, match="unknown Zenoh mode"):
        BusConfig.from_env()


def _wait(predicate, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()


def test_round_trip_through_a_service_process(tmp_path: Path) -> None:
    hub = f"tcp/127.0.0.1:{free_loopback_port()}"
    bus = Bus(BusConfig(mode="peer", listen=[hub]), "busrobot")
    poses: list[OdometryPose] = []
    statuses: dict[str, ServiceStatus] = {}
    lock = threading.Lock()
    bus.subscribe(bus.keys.odometry, OdometryPose, lambda m: poses.append(m))

    def on_status(s: ServiceStatus) -> None:
        with lock:
            statuses[s.state] = s

    bus.subscribe(bus.keys.status_all, ServiceStatus, on_status)
    proc = subprocess.Popen(
        [sys.executable, "-m", "semmap.services.odometry", "--robot", "busrobot", "--connect", hub, "--instance", "odo",
         "--set", "odometry.mode=gt", "--out", str(tmp_path)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
    )
    try:
        assert _wait(lambda: "running" in statuses, 30), "service never reported running"
        frames = bus.publisher(bus.keys.frames)
        assert frames.wait_matching(10)
        raw = bus.publisher(bus.keys.frames)
        raw.put_bytes(b"this is not msgpack")  # must be rejected and counted, not crash the service
        rgb = np.zeros((24, 32, 3), np.uint8)
        depth = np.full((24, 32), 1000, np.uint16)
        # a valid frame that names another robot on our key: a counted skip
        frames.put(Frame.from_arrays("otherbot", 0, 0.0, rgb, depth, 0.001, K, np.eye(4)))
        truth = []
        for i in range(5):
            pose = np.eye(4)
            pose[:3, 3] = [0.1 * i, 0.0, 0.0]
            truth.append(pose)
            frames.put(Frame.from_arrays("busrobot", i, i / 30, rgb, depth, 0.001, K, pose))
        assert _wait(lambda: len(poses) == 5, 15), f"got {len(poses)} poses"
        assert [p.frame_id for p in poses] == list(range(5))
        for p, t in zip(poses, truth, strict=True):
            np.testing.assert_allclose(p.pose, t)
        bus.publisher(bus.keys.control).put(Control("busrobot", "end_of_stream", 4, 5))
        assert _wait(lambda: "finished" in statuses, 10)
        assert statuses["finished"].counters.get("rejected[frames]") == 1
        assert statuses["finished"].counters.get("wrong_robot") == 1
        bus.publisher(bus.keys.control).put(Control("busrobot", "stop"))
        assert proc.wait(timeout=15) == 0
        lines = (tmp_path / "trajectory_odometry.tum").read_text().splitlines()
        assert len([ln for ln in lines if not ln.startswith("#")]) == 5
    finally:
        if proc.poll() is None:
            proc.kill()
        bus.close()
