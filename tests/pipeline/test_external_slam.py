"""The external-SLAM interface: the example client (its own process) gives the same map as the built-in front end
fed the same poses; live map queries over Zenoh answer what map.json holds."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from semmap.datasets import open_dataset
from semmap.datasets.trajectory_io import read_tum, write_tum
from semmap.runtime.client import SemmapClient
from semmap.runtime.maps.map_query import MapQuery
from semmap.runtime.maps.map_store import read_map_json

PROJECT = Path(__file__).resolve().parents[2]
SYNTH = "synthetic:frames=40"


def _external_run(semmap_run, out: Path, router, *extra: str) -> tuple[threading.Thread, dict]:  # noqa: ANN001
    """`semmap run external --out OUT ... EXTRA` started in a thread on the router; its result lands in
    `outcome["run"]` once the thread is joined."""
    outcome: dict = {}
    runner = threading.Thread(target=lambda: outcome.setdefault("run", semmap_run(
        ["external", "--out", str(out), "--no-viz", "--connect", router.endpoint, "--zenoh-mode", "client", *extra],
        timeout=900)))
    runner.start()
    return runner, outcome


def _drifted_trajectory(path: Path) -> None:
    """A SLAM-like estimate: the synthetic ground truth with a slow drift."""
    poses = []
    for i, (stamp, pose) in enumerate(open_dataset(SYNTH).groundtruth()):
        drifted = pose.copy()
        drifted[:3, 3] += [0.002 * i, -0.001 * i, 0.0]
        poses.append((stamp, drifted))
    write_tum(path, poses)


def test_example_client_gives_the_same_map_as_the_builtin_front_end(tmp_path: Path, router, semmap_run) -> None:
    trajectory = tmp_path / "slam.tum"
    _drifted_trajectory(trajectory)
    builtin = tmp_path / "builtin"
    # (the client's poses are the odometry as they are: the built-in run copies the file too, unchecked)
    result = semmap_run([SYNTH, "--out", str(builtin), "--odometry", f"file:{trajectory}", "--no-viz",
                         "--set", "odometry.repair=false"])
    assert result.returncode == 0, result.stderr[-3000:]

    external = tmp_path / "external"
    outcome: dict = {}

    def run_semmap() -> None:
        outcome["run"] = semmap_run(["external", "--out", str(external), "--no-viz", "--connect", router.endpoint,
                                     "--zenoh-mode", "client", "--set", "detector.kind=oracle"])

    runner = threading.Thread(target=run_semmap)
    runner.start()
    client = subprocess.run([sys.executable, "examples/slam_from_tum.py", SYNTH, str(trajectory), "--connect",
                             router.endpoint], cwd=PROJECT, capture_output=True, text=True, timeout=300,
                            env={**os.environ, "CI": "true"})
    runner.join(timeout=300)
    assert client.returncode == 0, client.stderr[-3000:]
    assert outcome["run"].returncode == 0, outcome["run"].stderr[-3000:]
    assert json.loads((external / "map.json").read_text()) == json.loads((builtin / "map.json").read_text())
    assert (external / "trajectory_optimized.tum").read_text() == (builtin / "trajectory_optimized.tum").read_text()
    # the SLAM's input poses are kept too, so `semmap eval` compares them with semmap's output
    assert (external / "trajectory_odometry.tum").read_text() == (builtin / "trajectory_odometry.tum").read_text()


@pytest.mark.needs_data
@pytest.mark.needs_model
def test_live_queries_match_map_json_on_7scenes(tmp_path: Path, router, semmap_run, data_root: Path) -> None:
    out = tmp_path / "run"
    outcome: dict = {}
    runner = threading.Thread(target=lambda: outcome.setdefault("run", semmap_run(
        ["external", "--out", str(out), "--no-viz", "--connect", router.endpoint, "--zenoh-mode", "client"],
        timeout=400)))
    runner.start()
    dataset = open_dataset(str(data_root / "7scenes-redkitchen"))
    frames = 90
    with SemmapClient("robot1", router.endpoint) as client:
        client.wait_ready(timeout=120)
        for i in range(frames):
            f = dataset[i]
            client.publish_frame(i, f.stamp, f.rgb, f.depth, f.depth_scale, f.intrinsics)  # (the one Intrinsics type)
            client.publish_pose(i, f.stamp, f.gt_pose, sigma_translation=2e-4, sigma_rotation=2e-4)
            client.wait_frame_done(i, timeout=120)
        everything = client.query_map()
        assert everything, "the first 90 frames show cups and chairs"
        first = everything[0]
        by_class = client.query_map(MapQuery(class_name=first.class_name))
        near = client.query_map(MapQuery(near=first.centroid, radius=0.5))
        by_id = client.query_map(MapQuery(ids=frozenset({first.id})))
        client.end_of_stream(frames - 1)
    runner.join(timeout=300)
    assert outcome["run"].returncode == 0, outcome["run"].stderr[-3000:]
    saved = {lm.id: lm for lm in read_map_json(out / "map.json")}
    assert {lm.id for lm in everything} == set(saved)
    for lm in everything:
        assert np.allclose(lm.centroid, saved[lm.id].centroid, atol=1e-4) and lm.class_name == saved[lm.id].class_name
    assert {lm.id for lm in by_class} == {i for i, lm in saved.items() if lm.class_name == first.class_name}
    assert {lm.id for lm in near} == {i for i, lm in saved.items()
                                      if np.linalg.norm(np.subtract(lm.centroid, first.centroid)) <= 0.5}
    assert [lm.id for lm in by_id] == [first.id]
    # the CLI on the saved map answers the same
    cli = subprocess.run([sys.executable, "-m", "semmap.cli", "query", str(out), "--class", first.class_name,
                          "--json"], cwd=PROJECT, capture_output=True, text=True, timeout=60)
    assert cli.returncode == 0, cli.stderr
    assert {lm["id"] for lm in json.loads(cli.stdout)["landmarks"]} == {lm.id for lm in by_class}


@pytest.mark.slow
@pytest.mark.needs_data
@pytest.mark.needs_model
def test_a_live_slam_is_checked_and_repaired(tmp_path: Path, router, semmap_run, data_root: Path) -> None:
    """`semmap run external --check-slam` with a client that publishes its SLAM's poses on the `slam` key: the
    SLAM (ORB-SLAM3's own trajectory of the Bonn crowd window, dragged by the walking people) is checked step by
    step against semmap's people-masked registration; the odometry the backend gets is repaired, the SLAM's own
    poses are kept beside it, and `semmap eval --groundtruth` scores both."""
    from semmap.algorithms.evaluation import ate_rmse, evaluate_run
    from semmap.algorithms.odometry.frontends import match_trajectory
    from semmap.datasets.trajectory_io import read_tum

    bonn = data_root / "bonn_crowd"
    slam_file = data_root / "orbslam3" / "bonn_crowd_orbslam3_run1.tum"
    if not slam_file.is_file():
        pytest.skip("no shared ORB-SLAM3 trajectory of the Bonn window")
    out = tmp_path / "run"
    runner, outcome = _external_run(semmap_run, out, router, "--check-slam")
    dataset = open_dataset(str(bonn))
    slam = read_tum(slam_file)
    stamps = np.array([t for t, _ in slam])
    frames = 150
    with SemmapClient("robot1", router.endpoint, check_slam=True) as client:
        client.wait_ready(timeout=120)
        for i in range(frames):
            f = dataset[i]
            client.publish_frame(i, f.stamp, f.rgb, f.depth, f.depth_scale, f.intrinsics)  # (the one Intrinsics type)
            nearest, ok = match_trajectory(stamps, np.array([f.stamp]))
            if ok[0]:
                client.publish_pose(i, f.stamp, slam[int(nearest[0])][1])
            client.wait_frame_done(i, timeout=180)
        client.end_of_stream(frames - 1)
    runner.join(timeout=600)
    assert outcome["run"].returncode == 0, outcome["run"].stderr[-3000:]
    report = json.loads((out / "odometry_repair.json").read_text())
    assert report["mode"] == "external" and report["counters"]["repair_steps"] == frames - 1
    assert report["counters"]["repair_overruled"] > 20 and report["overruled_spans"]
    result = evaluate_run(out, bonn / "groundtruth.txt")
    assert result["ate_slam_m"] > 2 * result["ate_odometry_m"], result
    gt = read_tum(bonn / "groundtruth.txt")
    assert ate_rmse(gt, read_tum(out / "trajectory_slam.tum")) == pytest.approx(result["ate_slam_m"])


@pytest.mark.slow
@pytest.mark.needs_data
def test_an_external_camera_is_posed_by_semmaps_own_orbslam3(tmp_path: Path, router, semmap_run,
                                                              data_root: Path) -> None:
    """`semmap run external --odometry orbslam3`: a robot's camera (a client, as `semmap ros2` is one) sends frames
    and the run poses them with its own ORB-SLAM3; the poses the client has are not sent (counted), the run file
    says so, and the trajectory follows the camera (TUM fr1_rpy window: within a few centimetres)."""
    from semmap.algorithms.evaluation import ate_rmse
    from semmap.datasets.trajectory_io import read_tum

    rpy = data_root / "tum_freiburg1_rpy"
    vocabulary = data_root / "orbslam3" / "ORBvoc_redkitchen_k10L5.txt"
    if not vocabulary.is_file():
        pytest.skip("no shared ORB vocabulary")
    out = tmp_path / "run"
    runner, outcome = _external_run(semmap_run, out, router, "--odometry", "orbslam3", "--set",
                                    f"odometry.orbslam3_vocabulary={vocabulary}")
    dataset = open_dataset(str(rpy))
    frames = 60
    from semmap.runtime.transport.run_registry import RunNotFound, find_run

    deadline = time.monotonic() + 120
    while True:  # (the run file appears once the run's bus is up)
        try:
            info = find_run(str(out), None)
            break
        except (RunNotFound, OSError, ValueError):
            assert time.monotonic() < deadline, "the run never registered"
            time.sleep(0.2)
    client = SemmapClient("robot1", router.endpoint, front_end=info.front_end)
    assert info.front_end == "orbslam3" and not info.check_slam
    with client:
        client.wait_ready(timeout=120)
        for i in range(frames):
            f = dataset[i]
            client.publish_frame(i, f.stamp, f.rgb, f.depth, f.depth_scale, f.intrinsics)
            client.publish_pose(i, f.stamp, np.eye(4))  # (a robot's own odometry: not sent)
            client.wait_frame_done(i, timeout=180)
        client.end_of_stream(frames - 1)
        assert client.poses_not_sent == frames
    runner.join(timeout=600)
    assert outcome["run"].returncode == 0, outcome["run"].stderr[-3000:]
    assert "ORB-SLAM3" in outcome["run"].stderr + outcome["run"].stdout
    stats = json.loads((out / "stats.json").read_text())
    assert stats["odometry"]["mode"] == "orbslam3"
    odometry = read_tum(out / "trajectory_odometry.tum")
    assert len(odometry) >= 0.9 * frames
    assert ate_rmse(read_tum(rpy / "groundtruth.txt"), odometry) < 0.06
    # beside it, ORB-SLAM3's own poses, and as it refined them at its end (what it alone would save)
    slam, refined = read_tum(out / "trajectory_slam.tum"), read_tum(out / "trajectory_slam_refined.tum")
    assert [t for t, _ in refined] == pytest.approx([t for t, _ in slam])
    assert ate_rmse(read_tum(rpy / "groundtruth.txt"), refined) < 0.06
    # ...which the odometry service offered the backend at the end (`odometry/refined`), and the backend decided on
    # it (taken, or withheld with its reason) before it wrote the trajectory: the run did not wait it out
    counters = {name: s["counters"] for name, s in stats["services"].items()}
    assert "refinement_frames" in counters["odometry"]  # (0 where it was withheld: ORB-SLAM3 lost its map)
    backend = counters["backend"]
    assert backend.get("odometry_refined_frames", 0) + backend.get("odometry_refinement_withheld", 0) > 0, backend
    assert "odometry_refinement_timeouts" not in backend
    if backend.get("odometry_refined_frames"):  # (every frame it sent is taken or counted as passed over)
        assert (backend["odometry_refined_frames"] + backend["odometry_refinement_passed_over"]
                == counters["odometry"]["refinement_frames"]), backend


@pytest.mark.slow
@pytest.mark.needs_data
def test_a_camera_that_does_not_wait_has_every_frame_posed_by_semmaps_orbslam3(tmp_path: Path, router, semmap_run,
                                                                                data_root: Path) -> None:
    """`semmap run external --odometry orbslam3` without `--realtime`, fed as a camera feeds it (30 Hz, never
    waiting for semmap): each frame waits for its dynamic objects behind the ones before it, and every one is
    posed, in order. (A single waiting slot once let each frame replace the one before: 1 pose of 300.)"""
    vocabulary = data_root / "orbslam3" / "ORBvoc_redkitchen_k10L5.txt"
    if not vocabulary.is_file():
        pytest.skip("no shared ORB vocabulary")
    rpy = data_root / "tum_freiburg1_rpy"
    out = tmp_path / "run"
    runner, outcome = _external_run(semmap_run, out, router, "--odometry", "orbslam3", "--set",
                                    f"odometry.orbslam3_vocabulary={vocabulary}")
    dataset = open_dataset(str(rpy))
    frames = 60
    with SemmapClient("robot1", router.endpoint) as client:
        client.wait_ready(timeout=120)
        for i in range(frames):
            f = dataset[i]
            client.publish_frame(i, f.stamp, f.rgb, f.depth, f.depth_scale, f.intrinsics)
            time.sleep(1 / 30)
        client.end_of_stream(frames - 1)
    runner.join(timeout=600)
    assert outcome["run"].returncode == 0, outcome["run"].stderr[-3000:]
    stats = json.loads((out / "stats.json").read_text())
    odometry = stats["services"]["odometry"]["counters"]
    assert odometry["poses_published"] == frames, odometry
    assert len(read_tum(out / "trajectory_odometry.tum")) >= 0.9 * frames
