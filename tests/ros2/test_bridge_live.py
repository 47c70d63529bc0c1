"""The bridge fed as a robot feeds it: a camera node in its own process publishes a recording on a clock (30 Hz,
640x480 rgb8 + 16UC1 + CameraInfo + Odometry), never waiting for anyone, into `semmap ros2` and `semmap run
external`. Lockstep with the documented settings (`lockstep:=true reliable_input:=true`): every frame the camera
sent is processed, the last included, and the map equals the folder's. Real time (best effort, defaults): the
map has landmarks, and every frame the camera sent is either processed or counted as lost by reason."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tests.ros2.recordings import raw_recording

pytest.importorskip("rclpy", reason="ROS 2 wheels absent: ./dev.sh setup installs the ros2 extra (semmap[ros2])")

PROJECT = Path(__file__).resolve().parents[2]
NODES = Path(__file__).with_name("ros_nodes.py")


@pytest.fixture
def ros_env(tmp_path: Path) -> dict:
    """Discovery on this host only, a domain of its own; the camera loads the profile the bridge writes (as a
    user is told to), the bridge loads its own by default."""
    env = {
        **os.environ,
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "ROS_DOMAIN_ID": str(100 + (os.getpid() + 37) % 100),
        "CI": "true",
        "ROS_LOG_DIR": str(tmp_path / "roslog"),
        "PYTHONPATH": str(PROJECT),
        "XDG_RUNTIME_DIR": str(tmp_path / "runtime"),
    }
    env.pop("FASTDDS_DEFAULT_PROFILES_FILE", None)
    return env


def live_session(
    tmp_path: Path,
    dataset: Path,
    frames: int,
    router,  # noqa: ANN001
    semmap_run,  # noqa: ANN001
    ros_env: dict,
    bridge_params: list[str],
    camera_args: list[str],
    listen_frames: int,
) -> tuple[dict, dict, dict, Path]:
    """`semmap run external` + `semmap ros2` + a listener + the camera node: (what the listener recorded, what
    the camera reports it sent, the run's stats.json, the run's out dir)."""
    out = tmp_path / "external"
    outcome: dict = {}
    run_args = ["external", "--out", str(out), "--no-viz", "--connect", router.endpoint, "--zenoh-mode", "client"]
    runner = threading.Thread(target=lambda: outcome.setdefault("run", semmap_run(run_args, timeout=500)))
    runner.start()
    logs = tmp_path / "logs"
    logs.mkdir()
    procs: dict[str, subprocess.Popen] = {}
    profile = tmp_path / "fastdds.xml"
    subprocess.run(
        [sys.executable, "-m", "semmap.cli", "ros2", "--write-fastdds-profile", str(profile)],
        cwd=PROJECT,
        env=ros_env,
        check=True,
        capture_output=True,
    )

    def start(name: str, argv: list[str], env: dict) -> None:
        procs[name] = subprocess.Popen(
            argv,
            cwd=PROJECT,
            env=env,
            stdout=open(logs / f"{name}.log", "w"),  # noqa: SIM115
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )

    listened = tmp_path / "listened.json"
    sent = tmp_path / "camera.json"
    try:
        deadline = time.monotonic() + 120  # the run records its endpoint, robot and run id: the bridge finds it
        while not (out / "run.json").exists():
            assert time.monotonic() < deadline and runner.is_alive(), "semmap run external wrote no run.json"
            time.sleep(0.1)
        bridge = [sys.executable, "-m", "semmap.cli", "ros2", "--run", str(out), "--zenoh-mode", "client"]
        bridge += ["--ros-args", "-r", "/odom:=/slam/odom"]
        for item in bridge_params:
            bridge += ["-p", item]
        start("bridge", bridge, ros_env)
        start("listener", [sys.executable, str(NODES), "listen", str(listened), str(listen_frames)], ros_env)
        deadline = time.monotonic() + 60
        while not listened.with_suffix(".ready").exists():
            assert time.monotonic() < deadline and procs["listener"].poll() is None, (logs / "bridge.log").read_text()
            time.sleep(0.1)
        camera_env = {**ros_env, "FASTDDS_DEFAULT_PROFILES_FILE": str(profile)}
        camera = [sys.executable, str(NODES), "camera", str(dataset), str(frames), str(sent), *camera_args]
        start("camera", camera, camera_env)
        assert procs["camera"].wait(timeout=300) == 0, (logs / "camera.log").read_text()[-3000:]
        assert procs["listener"].wait(timeout=400) == 0, (logs / "bridge.log").read_text()[-3000:]
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGINT)
        for proc in procs.values():
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        runner.join(timeout=300)
    assert procs["bridge"].returncode == 0, (logs / "bridge.log").read_text()[-3000:]
    assert outcome["run"].returncode == 0, outcome["run"].stderr[-3000:]
    stats = json.loads((out / "stats.json").read_text())
    return json.loads(listened.read_text()), json.loads(sent.read_text()), stats, out


def _landmarks(out: Path) -> list[dict]:
    return json.loads((out / "map.json").read_text())["landmarks"]


LOCKSTEP_FRAMES = 150
# the bridge declares the same per-frame sigmas as `--odometry gt` (the camera sends the recording's ground truth)
GT_SIGMAS = ["sigma_translation_m:=0.0002", "sigma_rotation_deg:=0.01"]


@pytest.mark.slow
@pytest.mark.needs_model
def test_lockstep_with_the_documented_settings_processes_every_frame_the_camera_sent(
    tmp_path: Path, kitchen_dir: Path, router, semmap_run, ros_env: dict
) -> None:
    """A reliable camera at 30 Hz that never waits (a recording played as it was recorded); the bridge with
    `lockstep:=true reliable_input:=true` and nothing else: all frames processed, the last one included, and the
    landmarks equal those of `semmap run --odometry gt --lockstep` on the same raw images recorded in a bag (ids,
    classes, centroids to 1 mm)."""
    folder = tmp_path / "folder"
    result = semmap_run(
        [str(raw_recording(tmp_path, kitchen_dir, LOCKSTEP_FRAMES)), "--out", str(folder), "--odometry", "gt",
         "--lockstep", "--no-viz"]
        + ["--max-frames", str(LOCKSTEP_FRAMES)],
        timeout=500,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    want = _landmarks(folder)
    assert len(want) >= 3
    params = ["lockstep:=true", "reliable_input:=true", "end_after_idle_s:=4.0", *GT_SIGMAS]
    state, camera, stats, out = live_session(
        tmp_path, kitchen_dir, LOCKSTEP_FRAMES, router, semmap_run, ros_env, params, ["--reliable"], LOCKSTEP_FRAMES
    )
    assert camera["sent"] == LOCKSTEP_FRAMES and camera["late_frames"] == 0, camera
    status = state["status"]
    assert status["received"]["colour"] == LOCKSTEP_FRAMES, status
    assert status["frames_sent"] == LOCKSTEP_FRAMES and status["frames_done"] == LOCKSTEP_FRAMES, status
    assert status["lost"] == {"total": 0}, status
    assert status["input_history"] == "keep all"
    assert stats["frames"]["processed"] == LOCKSTEP_FRAMES
    assert stats["frames"]["published"] == LOCKSTEP_FRAMES, stats["frames"]  # what the bridge sent
    assert stats["source"]["counters"] == {"total": 0}
    got = _landmarks(out)
    assert [(lm["id"], lm["class"]) for lm in got] == [(lm["id"], lm["class"]) for lm in want]
    for a, b in zip(got, want, strict=True):
        assert np.allclose(a["centroid"], b["centroid"], atol=1e-3), (a, b)
    path = state["path"]
    assert path is not None and len(path["poses"]) == LOCKSTEP_FRAMES  # the last frame's pose included


REALTIME_FRAMES = 300


@pytest.mark.slow
@pytest.mark.needs_model
def test_real_time_at_30_hz_best_effort_maps_and_counts_every_lost_frame(
    tmp_path: Path, kitchen_dir: Path, router, semmap_run, ros_env: dict
) -> None:
    """A best-effort camera at 30 Hz (a RealSense node's QoS), the bridge with its defaults (real time, best
    effort, its Fast DDS profile): the map has >= 3 landmarks of >= 2 classes, and every frame the camera sent is
    either processed by semmap or counted in /semmap/bridge_status by reason."""
    state, camera, stats, out = live_session(
        tmp_path, kitchen_dir, REALTIME_FRAMES, router, semmap_run, ros_env, ["end_after_idle_s:=3.0"], [], 0
    )
    status = state["status"]
    lost = status["lost"]
    print(json.dumps({"camera": camera, "status": status, "frames": stats["frames"]}, indent=1))
    assert camera["sent"] == REALTIME_FRAMES
    # the transport with the profile on both sides: (nearly) everything arrives
    assert status["received"]["colour"] >= 0.9 * REALTIME_FRAMES, status
    processed = stats["frames"]["processed"]
    assert stats["frames"]["published"] == status["frames_sent"], (stats["frames"], status)
    assert processed == status["frames_sent"], "semmap processes every frame it is sent (detecting some)"
    # every frame the camera sent: processed, or lost for a counted reason
    assert processed + lost["total"] - lost.get("not_processed", 0) == camera["sent"], (processed, lost)
    # ... and the run's stats.json has the bridge's count of frames lost before semmap
    assert stats["source"]["counters"]["total"] == lost["total"] - lost.get("not_processed", 0)
    landmarks = _landmarks(out)
    classes = {lm["class"] for lm in landmarks}
    assert len(landmarks) >= 3 and len(classes) >= 2, landmarks
    assert len(state["markers"]) == len(landmarks)
