"""The ROS 2 bridge with real rclpy nodes, each its own process, discovery on this host only: a camera + SLAM node
publishes 7-Scenes frames; `semmap ros2` feeds `semmap run external`; the landmarks on /semmap/landmarks equal
those of `semmap run` on the folder with the same poses from a file."""

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

from semmap.core.messages import DynamicObjects
from semmap.datasets import open_dataset
from semmap.datasets.ros_convert import quaternion_matrix
from semmap.datasets.trajectory_io import write_tum
from semmap.runtime.client import SemmapClient
from tests.ros2.recordings import raw_recording

pytest.importorskip("rclpy", reason="ROS 2 wheels absent: ./dev.sh setup installs the ros2 extra (semmap[ros2])")

PROJECT = Path(__file__).resolve().parents[2]
NODES = Path(__file__).with_name("ros_nodes.py")
FRAMES = 60


@pytest.fixture
def ros_env(tmp_path: Path) -> dict:
    """Discovery on this host only, a domain of its own (tests running side by side do not see each other)."""
    domain = str(100 + os.getpid() % 100)
    return {
        **os.environ,
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "ROS_DOMAIN_ID": domain,
        "CI": "true",
        "ROS_LOG_DIR": str(tmp_path / "roslog"),
        "PYTHONPATH": str(PROJECT),
    }


def _map(out: Path) -> list[dict]:
    return json.loads((out / "map.json").read_text())["landmarks"]


def _bridge_session(
    tmp_path: Path,
    dataset: Path,
    frames: int,
    out: Path,
    router,  # noqa: ANN001
    semmap_run,  # noqa: ANN001
    ros_env: dict,
    run_args: list[str],
) -> tuple[dict, subprocess.CompletedProcess]:
    """`semmap run external` + `semmap ros2` (lockstep) + a camera node publishing `frames` frames of `dataset` (and
    the bad messages) + a listener node: what the listener recorded, and the run's result. Every process ended
    cleanly (rc 0) or the test fails."""
    outcome: dict = {}
    runner = threading.Thread(
        target=lambda: outcome.setdefault(
            "run",
            semmap_run(
                [
                    "external",
                    "--out",
                    str(out),
                    "--no-viz",
                    "--connect",
                    router.endpoint,
                    "--zenoh-mode",
                    "client",
                    *run_args,
                ],
                timeout=500,
            ),
        )
    )
    runner.start()
    logs = tmp_path / "logs"
    logs.mkdir()
    procs: dict[str, subprocess.Popen] = {}

    def start(name: str, argv: list[str]) -> None:
        procs[name] = subprocess.Popen(
            argv,
            cwd=PROJECT,
            env=ros_env,
            stdout=open(logs / f"{name}.log", "w"),  # noqa: SIM115
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )

    listened = tmp_path / "listened.json"
    try:
        start(
            "bridge",
            [
                sys.executable,
                "-m",
                "semmap.cli",
                "ros2",
                "--connect",
                router.endpoint,
                "--zenoh-mode",
                "client",
                "--ros-args",
                "-r",
                "/odom:=/slam/odom",
                "-p",
                "lockstep:=true",
                "-p",
                "reliable_input:=true",
                "-p",
                "input_depth:=200",
                "-p",
                "end_after_idle_s:=4.0",
                "-p",
                "max_wait_s:=60.0",
            ],
        )
        start("listener", [sys.executable, str(NODES), "listen", str(listened), str(frames)])
        # /semmap/dynamic is volatile (a late subscriber misses what went before): frames start once it is matched
        deadline = time.monotonic() + 60
        while not listened.with_suffix(".ready").exists():
            assert time.monotonic() < deadline and procs["listener"].poll() is None, (logs / "bridge.log").read_text()
            time.sleep(0.1)
        start("camera", [sys.executable, str(NODES), "publish", str(dataset), str(frames), "--bad"])
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
    return json.loads(listened.read_text()), outcome["run"]


@pytest.mark.needs_model
def test_bridge_maps_like_the_folder_and_skips_bad_messages(
    tmp_path: Path, kitchen_dir: Path, router, semmap_run, ros_env: dict
) -> None:
    dataset = open_dataset(kitchen_dir)
    trajectory = tmp_path / "slam.tum"
    write_tum(trajectory, [(dataset[i].stamp, dataset[i].gt_pose) for i in range(FRAMES)])
    folder = tmp_path / "folder"
    result = semmap_run(
        [
            str(raw_recording(tmp_path, kitchen_dir, FRAMES)),
            "--out",
            str(folder),
            "--odometry",
            f"file:{trajectory}",
            "--max-frames",
            str(FRAMES),
            "--no-viz",
        ],
        timeout=400,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    want = _map(folder)
    assert len(want) >= 3, "the first two seconds show a cup, chairs and a table"

    external = tmp_path / "external"
    state, _ = _bridge_session(tmp_path, kitchen_dir, FRAMES, external, router, semmap_run, ros_env, [])
    status = state["status"]
    assert status["frames_sent"] == FRAMES and status["frames_done"] == FRAMES and status["ended"]
    # the bad messages were counted and skipped; none of them became a frame
    assert status["sync"]["bad_colour"] == 1 and status["sync"]["size_mismatch"] == 1
    assert status["sync"]["bad_pose"] == 1 and status["sync"]["matched"] == FRAMES
    markers = state["markers"]
    assert [m["id"] for m in markers] == [lm["id"] for lm in want]
    assert [m["label"] for m in markers] == [f"{lm['class']} #{lm['id']}" for lm in want]
    for m, lm in zip(markers, want, strict=True):
        assert np.allclose(m["centroid"], lm["centroid"], atol=1e-3), (m, lm)
        assert np.allclose(m["scale"], np.maximum(lm["extent"], 0.02), atol=1e-3)
        assert m["frame"] == "world"  # the SLAM's frame (the pose messages' header)
    colours = {m["label"].split(" #")[0]: tuple(m["colour"]) for m in markers}
    assert all(tuple(m["colour"]) == colours[m["label"].split(" #")[0]] for m in markers)  # one colour per class
    # the optimised trajectory arrived, one pose per frame, at the frames' stamps
    path = state["path"]
    assert path is not None and len(path["poses"]) == FRAMES and path["frame"] == "world"
    assert np.allclose([p[0] for p in path["poses"]], [dataset[i].stamp for i in range(FRAMES)], atol=1e-6)
    assert [lm["id"] for lm in _map(external)] == [lm["id"] for lm in want]


DYNAMIC_FRAMES = 40


@pytest.mark.needs_data
@pytest.mark.needs_model
def test_bridge_publishes_the_dynamic_objects_as_short_lived_boxes(
    tmp_path: Path, data_root: Path, router, semmap_run, ros_env: dict
) -> None:
    """Bonn "crowd" (people walking round a hand-held camera) through the bridge: for every detected frame with
    dynamic objects, one MarkerArray on /semmap/dynamic at the frame's stamp, a cube and a label per object that
    semmap published on its `dynamic` key (the reference, received here over Zenoh), the cube where the image box
    and its depth range put it with the frame's pose, a colour per track, a lifetime so that stale boxes vanish."""
    bonn = data_root / "bonn_crowd"
    if not bonn.is_dir():
        pytest.skip("bonn_crowd absent from the shared data")
    dataset = open_dataset(bonn)
    frames = [dataset[i] for i in range(DYNAMIC_FRAMES)]
    reference: dict[int, DynamicObjects] = {}
    lock = threading.Lock()

    def keep(message: DynamicObjects) -> None:
        with lock:
            reference[message.frame_id] = message

    with SemmapClient("robot1", router.endpoint, "client") as client:
        client.on_dynamic(keep)
        state, _ = _bridge_session(tmp_path, bonn, DYNAMIC_FRAMES, tmp_path / "run", router, semmap_run, ros_env, [])
    assert sorted(reference) == list(range(DYNAMIC_FRAMES))
    arrays = [a for a in state["dynamic"] if a]
    stamps = np.array([a[0]["stamp"] for a in arrays])
    assert np.all(np.diff(stamps) > 0.01), "one MarkerArray per frame, in order"

    def array_at(t: float) -> list | None:
        near = np.flatnonzero(np.abs(stamps - t) < 1e-4)
        return arrays[int(near[0])] if len(near) else None

    published = 0
    for frame_id, objects in sorted(reference.items()):
        boxes = [b for b in objects.boxes if b.depth_max_m > 0]
        array = array_at(objects.stamp)
        if objects.skipped or not boxes:
            assert array is None, (frame_id, objects.skipped)
            continue
        assert array is not None, f"frame {frame_id}: {len(boxes)} dynamic boxes, no MarkerArray"
        frame = frames[frame_id]
        assert abs(objects.stamp - frame.stamp) < 1e-5
        cubes = {m["id"]: m for m in array if m["ns"] == "dynamic"}
        labels = {m["id"]: m for m in array if m["ns"] == "dynamic_labels"}
        assert sorted(cubes) == sorted(labels) == sorted(b.track_id for b in boxes)
        k, pose = frame.intrinsics, frame.gt_pose  # the camera node sent the ground truth as the SLAM's pose
        colours = {tuple(np.round(m["colour"][:3], 3)) for m in cubes.values()}
        assert len(colours) == len(cubes), "a distinct colour per object"
        for box in boxes:
            cube, label = cubes[box.track_id], labels[box.track_id]
            assert cube["frame"] == label["frame"] == "world"
            assert cube["lifetime"] == pytest.approx(0.5) and label["lifetime"] == pytest.approx(0.5)
            assert label["text"] == f"{box.class_name} (track {box.track_id})" and box.reason == "class"
            # back in the camera: the cube's centre projects to the image box's centre at the middle of its
            # depth range; it is as wide and high as the box there, as deep as the range, along the optical axes
            c = pose[:3, :3].T @ (np.array(cube["position"]) - pose[:3, 3])
            x1, y1, x2, y2 = box.box
            assert c[2] == pytest.approx((box.depth_min_m + box.depth_max_m) / 2, abs=1e-4)
            assert k.fx * c[0] / c[2] + k.cx == pytest.approx((x1 + x2) / 2, abs=0.05)
            assert k.fy * c[1] / c[2] + k.cy == pytest.approx((y1 + y2) / 2, abs=0.05)
            want = [(x2 - x1) * c[2] / k.fx, (y2 - y1) * c[2] / k.fy, max(box.depth_max_m - box.depth_min_m, 0.05)]
            assert np.allclose(cube["scale"], want, atol=1e-4)
            q = np.array(cube["orientation"])
            assert np.allclose(quaternion_matrix(*q), pose[:3, :3], atol=1e-5)
            published += 1
    assert published >= 20, "people walk through most of these frames"
    assert {b.class_name for m in reference.values() for b in m.boxes} == {"person"}
    assert state["status"]["link"]["dynamic_boxes"] == published


def test_a_topic_that_never_arrives_is_reported_by_name_and_ctrl_c_stops_cleanly(tmp_path: Path, ros_env: dict) -> None:
    """No camera, no semmap: after topic_timeout_s the bridge names each silent input (as remapped); SIGINT ends it
    with exit code 0."""
    log = tmp_path / "bridge.log"
    with open(log, "w") as out:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "semmap.cli",
                "ros2",
                "--connect",
                "tcp/127.0.0.1:9",
                "--ros-args",
                "-r",
                "/odom:=/robot/odom",
                "-p",
                "topic_timeout_s:=1.0",
            ],
            cwd=PROJECT,
            env=ros_env,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:
            deadline = time.monotonic() + 60
            while "no message on /robot/odom" not in log.read_text(errors="replace"):
                assert proc.poll() is None and time.monotonic() < deadline, log.read_text(errors="replace")[-3000:]
                time.sleep(0.2)
        finally:
            os.killpg(proc.pid, signal.SIGINT)
            code = proc.wait(timeout=60)
    text = log.read_text(errors="replace")
    assert code == 0, text[-3000:]
    for topic in (
        "/camera/camera/color/image_raw",
        "/camera/camera/aligned_depth_to_color/image_raw",
        "/camera/camera/color/camera_info",
        "/robot/odom",
    ):
        assert f"no message on {topic}" in text
    assert '"missing_topics": ["/camera/camera/color/image_raw"' in text  # the final counters in the log
