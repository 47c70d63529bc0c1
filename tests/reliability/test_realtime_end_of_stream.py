"""The end of a real-time stream whose odometry dropped frames: the backend gives up the frames that never come
(counted) and finishes with the last one; a last frame whose odometry never comes is a stall, not an end.

Why: the odometry keeps only the newest frames under load, so a frame close to the end may never get a pose;
the backend waited for it until REALTIME_MAX_PENDING later poses came, which they never did at the end of the
stream, and the 3000-frame soak (tests/reliability/test_overload.py) failed after 150 s of "nothing moved".

A real backend process over a real Zenoh router, fed odometry and observations as the pipeline would.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from semmap.core.keys import Keys
from semmap.core.messages import Control, Observations, OdometryPose, ServiceStatus
from semmap.services.backend.service import REALTIME_MAX_PENDING
from tests.reliability.lockstep_feeder import PROJECT, LockstepFeeder, start_service

ROBOT = "rtend"
FRAMES = 40
LAST = FRAMES - 1
# the first frame dropped (the backend starts at the second, and counts the first at the end of the stream), one
# dropped mid-stream (given up once REALTIME_MAX_PENDING later poses wait) and one too close to the end
# for that to ever happen
DROPPED = {0, 10, LAST - 2}


def _pose(i: int) -> OdometryPose:
    pose = np.eye(4)
    pose[0, 3] = 0.01 * i
    return OdometryPose(ROBOT, i, 0.1 * i, pose, keyframe=True, sigma_translation=0.003,
                        sigma_rotation=math.radians(0.3), source="gt")


KEYS = Keys(ROBOT)


def _realtime_backend(tmp_path: Path, router) -> tuple[LockstepFeeder, subprocess.Popen, list[ServiceStatus]]:  # noqa: ANN001
    """A real-time backend process (no loop closure) fed by a test feeder; its status messages collected."""
    feeder = LockstepFeeder(router.endpoint, ROBOT, "backend", [KEYS.odometry, KEYS.observations])
    statuses: list[ServiceStatus] = []
    feeder.bus.subscribe(KEYS.status_all, ServiceStatus, statuses.append)
    proc = start_service("backend", router.endpoint, ROBOT, tmp_path, "--mode", "realtime",
                         "--set", "loop_closure.enabled=false")
    odometry, observations = feeder.publishers[KEYS.odometry], feeder.publishers[KEYS.observations]
    if not (odometry.wait_matching(30) and observations.wait_matching(30)):
        proc.kill()
        feeder.close()
        pytest.fail("the backend did not come up")
    return feeder, proc, statuses


def _wait(condition: threading.Condition, test, timeout: float) -> bool:  # noqa: ANN001
    with condition:
        return condition.wait_for(test, timeout=timeout)


def test_backend_ends_a_realtime_stream_past_dropped_odometry_but_not_past_a_missing_last_frame(
        tmp_path: Path, router) -> None:  # noqa: ANN001
    assert LAST - max(DROPPED) < REALTIME_MAX_PENDING, "the late drop must be one the bounded buffer cannot release"
    feeder, proc, statuses = _realtime_backend(tmp_path, router)
    odometry, observations = feeder.publishers[KEYS.odometry], feeder.publishers[KEYS.observations]
    log = tmp_path / "backend.log"
    try:
        for i in range(FRAMES):
            observations.put(Observations(ROBOT, i, 0.1 * i))
            if i not in DROPPED and i != LAST:
                odometry.put(_pose(i))
            time.sleep(0.005)
        feeder.control.put(Control(ROBOT, "end_of_stream", LAST, FRAMES))

        # every frame the odometry sent before the late drop goes through; then the backend waits, because the
        # last frame's pose has not come: it may still (a slow odometry), and if it never does the run's
        # watchdog fails the run (a stall), so finishing here would hide one
        assert _wait(feeder.changed, lambda: feeder.done >= max(DROPPED) - 1, 20), f"progress {feeder.done}"
        time.sleep(3.0)
        assert feeder.done == max(DROPPED) - 1, feeder.done
        assert "finished (last frame" not in log.read_text()

        odometry.put(_pose(LAST))  # the last pose: what is still missing before it never comes
        assert _wait(feeder.changed, lambda: feeder.done >= LAST, 20), log.read_text()[-3000:]
        deadline = time.monotonic() + 20
        while "finished (last frame" not in log.read_text() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert f"finished (last frame {LAST})" in log.read_text()
        feeder.control.put(Control(ROBOT, "stop"))
        assert proc.wait(timeout=30) == 0, log.read_text()[-3000:]
        time.sleep(0.5)
        final = statuses[-1]  # what the run's stats.json gets
        assert final.state == "finished", final
        assert final.counters["frames_without_odometry"] == len(DROPPED), final.counters
        assert final.counters["observations_unjoined"] == len(DROPPED), final.counters
        assert final.counters["frames"] == FRAMES - len(DROPPED)
        assert len(np.loadtxt(tmp_path / "trajectory_optimized.tum")) == FRAMES - len(DROPPED)
    finally:
        feeder.close()
        if proc.poll() is None:
            proc.kill()


@pytest.mark.slow
def test_a_realtime_run_whose_backend_hangs_still_fails_as_a_stall_naming_it(tmp_path: Path) -> None:
    """The other half: a real time run is not ended by giving up frames while a service is stuck. The backend is
    stopped (SIGSTOP: no progress, no status) once the stream runs; the run fails on its watchdog and says which
    service it waited on. (The stopped backend's full socket slows the player down, as Zenoh's blocking congestion
    control does; the other services move, slowly, until the stream is over, then nothing does.)"""
    out = tmp_path / "run"
    # the watchdog's limit is start_timeout_s + 2 * frame_timeout_s + 30 s (semmap/cli/run.py): 42 s here
    proc = subprocess.Popen([sys.executable, "-m", "semmap.cli", "run", "synthetic:frames=150", "--out", str(out),
                             "--realtime", "--no-viz", "--quiet", "--set", "run.start_timeout_s=10",
                             "--set", "run.frame_timeout_s=1"], cwd=PROJECT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "CI": "true"})
    stopped = 0
    try:
        assert proc.stderr is not None
        for line in proc.stderr:
            if "started backend (pid " in line:
                stopped = int(line.split("(pid ")[1].split(")")[0])
                break
        assert stopped, "the backend was not started"
        player_log = out / "logs" / "player.log"
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (player_log.is_file() and "pipeline ready" in player_log.read_text()):
            time.sleep(0.1)
        os.kill(stopped, signal.SIGSTOP)
        _, stderr = proc.communicate(timeout=400)
    finally:
        if stopped:
            with contextlib.suppress(ProcessLookupError):
                os.kill(stopped, signal.SIGCONT)
        if proc.poll() is None:  # the orchestrator stops its services on SIGTERM
            proc.terminate()
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=40)
            proc.kill()
    assert proc.returncode == 1, stderr[-3000:]
    assert "nothing moved for 42 s" in stderr and "waiting on backend (running, last frame" in stderr, stderr[-3000:]
    stats = json.loads((out / "stats.json").read_text())
    assert stats["outcome"] == "failed" and stats["failure"].startswith("nothing moved"), stats["failure"]


def test_a_service_that_fell_behind_follows_a_signed_stream_that_moved_on(tmp_path: Path, router, monkeypatch) -> None:  # noqa: ANN001
    """In a run (signed messages), a service that stood still while the stream moved on by more than
    `security.max_frame_gap` (stopped, starved, started late) used to refuse that stream forever: its reference
    stayed where it stood. After REANCHOR_AFTER refusals in a row that agree with each other, it follows (counted);
    an unsigned open stream never re-anchors (tests/security/test_hostile_peers.py: 2^40 stays refused)."""
    from semmap.runtime.transport.bus import Bus, BusConfig, RunTrust
    from semmap.runtime.transport.service import REANCHOR_AFTER

    run_id, secret = "reanchor", RunTrust.new_secret()
    monkeypatch.setenv("SEMMAP_RUN_ID", run_id)
    monkeypatch.setenv("SEMMAP_RUN_KEY", secret)
    keys = Keys(ROBOT)
    client = BusConfig(mode="client", connect=[router.endpoint], listen=[])
    buses = {role: Bus(client, ROBOT, RunTrust(run_id, bytes.fromhex(secret), role))
             for role in ("odometry", "associator", "player", "orchestrator")}
    odometry = buses["odometry"].publisher(keys.odometry)
    observations = buses["associator"].publisher(keys.observations)
    control = buses["player"].publisher(keys.control)
    statuses: list[ServiceStatus] = []
    buses["player"].subscribe(keys.status_all, ServiceStatus, statuses.append)
    proc = start_service("backend", router.endpoint, ROBOT, tmp_path, "--mode", "realtime",
                         "--set", "loop_closure.enabled=false")
    log = tmp_path / "backend.log"
    first, last = 1000, 1039  # the backend stands at frame -1; the stream is 1000 frames on
    try:
        assert odometry.wait_matching(30) and observations.wait_matching(30), "the backend did not come up"
        for i in range(first, last + 1):
            odometry.put(_pose(i))
            observations.put(Observations(ROBOT, i, 0.1 * i))
            time.sleep(0.01)
        control.put(Control(ROBOT, "end_of_stream", last, last + 1))
        deadline = time.monotonic() + 30
        while f"finished (last frame {last})" not in log.read_text() and time.monotonic() < deadline:
            time.sleep(0.1)
        text = log.read_text()
        assert f"finished (last frame {last})" in text, text[-3000:]
        assert "odometry moved on to frame" in text
        buses["orchestrator"].publisher(keys.control).put(Control(ROBOT, "stop"))
        assert proc.wait(timeout=30) == 0, log.read_text()[-3000:]
        time.sleep(0.5)
        counters = statuses[-1].counters
        assert counters["frame_gap_followed[odometry]"] == 1, counters
        assert counters["rejected_frame_gap[odometry]"] == REANCHOR_AFTER - 1, counters
        followed = first + REANCHOR_AFTER - 1
        assert len(np.loadtxt(tmp_path / "trajectory_optimized.tum")) == last + 1 - followed
    finally:
        for bus in buses.values():
            bus.close()
        if proc.poll() is None:
            proc.kill()


def test_backend_gives_up_a_pose_whose_observations_never_come_and_maps_the_rest(tmp_path: Path, router) -> None:  # noqa: ANN001
    """Two detector replicas in real time: replica 2 answered frame 1 before replica 1 answered frame 0 (its first
    inference), the tracker started at frame 1, and frame 0's observations never came. The poses (gt odometry,
    fast) were all here first; the backend waited on frame 0 for ever and dropped every later frame's
    observations as "unjoined": 0 frames mapped, a stall (`semmap run 7-Scenes --realtime --detectors 2`)."""
    feeder, proc, statuses = _realtime_backend(tmp_path, router)
    odometry, observations = feeder.publishers[KEYS.odometry], feeder.publishers[KEYS.observations]
    log = tmp_path / "backend.log"
    try:
        for i in range(FRAMES):  # the odometry runs ahead
            odometry.put(_pose(i))
            time.sleep(0.002)
        time.sleep(0.5)
        for i in range(1, FRAMES):  # frame 0's observations were lost upstream
            observations.put(Observations(ROBOT, i, 0.1 * i))
            time.sleep(0.005)
        feeder.control.put(Control(ROBOT, "end_of_stream", LAST, FRAMES))
        assert _wait(feeder.changed, lambda: feeder.done >= LAST, 20), log.read_text()[-3000:]
        deadline = time.monotonic() + 20
        while "finished (last frame" not in log.read_text() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert f"finished (last frame {LAST})" in log.read_text()
        assert "frame 0: its observations never came" in log.read_text()
        feeder.control.put(Control(ROBOT, "stop"))
        assert proc.wait(timeout=30) == 0, log.read_text()[-3000:]
        time.sleep(0.5)
        final = statuses[-1]
        assert final.counters["frames"] == FRAMES - 1, final.counters
        assert final.counters["frames_without_observations"] == 1, final.counters
        assert final.counters.get("observations_unjoined", 0) == 0, final.counters
        assert len(np.loadtxt(tmp_path / "trajectory_optimized.tum")) == FRAMES - 1
    finally:
        feeder.close()
        if proc.poll() is None:
            proc.kill()
