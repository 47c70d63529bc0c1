"""Dynamic scenes through the real pipeline: the `dynamic` key reaches an external subscriber for every frame,
the `rgbd` odometry waits in lockstep for each frame's boxes, and ground truth with gaps never stalls a run."""

from __future__ import annotations

import shutil
import threading
import time
from pathlib import Path

import pytest

from semmap.core.messages import DynamicObjects
from semmap.datasets.trajectory_io import read_tum, write_tum
from semmap.datasets.tum import TumDataset
from semmap.runtime.client import SemmapClient

SYNTH_FRAMES = 30


def test_an_external_subscriber_receives_every_frames_dynamic_objects(
    tmp_path: Path, router, semmap_run, read_stats
) -> None:
    received: dict[int, DynamicObjects] = {}
    lock = threading.Lock()

    def keep(message: DynamicObjects) -> None:
        with lock:
            received[message.frame_id] = message

    with SemmapClient("robot1", router.endpoint, "client") as client:
        client.on_dynamic(keep)
        out = tmp_path / "run"
        result = semmap_run(
            [
                f"synthetic:frames={SYNTH_FRAMES}",
                "--out",
                str(out),
                "--only",
                "detector,tracker",
                "--no-viz",
                "--connect",
                router.endpoint,
                "--zenoh-mode",
                "client",
            ]
        )
        assert result.returncode == 0, result.stderr[-3000:]
        deadline = time.monotonic() + 5
        while len(received) < SYNTH_FRAMES and time.monotonic() < deadline:
            time.sleep(0.05)
    assert sorted(received) == list(range(SYNTH_FRAMES))  # one per frame, the empty ones too
    boxes = [b for m in received.values() for b in m.boxes]
    assert boxes, "the synthetic room's walking people are dynamic by class"
    assert {b.class_name for b in boxes} == {"person"} and {b.reason for b in boxes} == {"class"}
    assert all(0 < b.depth_min_m <= b.depth_max_m < 10 for b in boxes)
    tracker = next(s for s in read_stats(out)["services"].values() if s["service"] == "tracker")
    assert tracker["counters"]["dynamic_boxes"] == len(boxes)


def _tum_subset(src: Path, dst: Path, frames: int, drop_gt: dict[int, int] | None = None, gt: bool = True) -> Path:
    """The first `frames` frames of a TUM folder; `drop_gt` {frame: n}: the n ground-truth samples either side of
    the one nearest to that frame are removed with it (30 Hz mocap: n=0 leaves a 67 ms gap)."""
    dst.mkdir(parents=True)
    for name in ("rgb.txt", "depth.txt"):
        lines = [ln for ln in (src / name).read_text().splitlines() if ln and not ln.startswith("#")][:frames]
        (dst / name).write_text("\n".join(lines) + "\n")
        for line in lines:
            rel = line.split()[1]
            (dst / rel).parent.mkdir(exist_ok=True)
            shutil.copy(src / rel, dst / rel)
    shutil.copy(src / "intrinsics.txt", dst / "intrinsics.txt")
    if gt:
        poses = read_tum(src / "groundtruth.txt")
        stamps = TumDataset(dst)._stamps
        gone: set[int] = set()
        for frame, n in (drop_gt or {}).items():
            k = min(range(len(poses)), key=lambda j: abs(poses[j][0] - stamps[frame]))
            gone.update(range(k - n, k + n + 1))
        write_tum(dst / "groundtruth.txt", [p for j, p in enumerate(poses) if j not in gone])
    return dst



def test_ground_truth_with_gaps_never_stalls_a_lockstep_run(
    bonn_dir: Path, tmp_path: Path, semmap_run, read_stats
) -> None:
    # frame 3: its ground-truth sample missing (a 67 ms gap: interpolated); frame 8: the samples of frames 7-9
    # missing (a 133 ms gap: frames 7, 8 and 9 have no pose)
    data = _tum_subset(bonn_dir, tmp_path / "gaps", 12, {3: 0, 8: 1})
    ds = TumDataset(data)
    stamps = ds._stamps
    assert ds.interpolated == 1 and ds[3].gt_pose is not None
    assert [i for i in range(len(ds)) if ds[i].gt_pose is None] == [7, 8, 9]
    out = tmp_path / "run"
    t0 = time.monotonic()
    result = semmap_run(
        [
            str(data),
            "--out",
            str(out),
            "--odometry",
            "gt",
            "--lockstep",
            "--only",
            "odometry",
            "--no-viz",
            "--set",
            "run.frame_timeout_s=20",
        ]
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert time.monotonic() - t0 < 60  # a stall would wait run.frame_timeout_s and fail the run
    stats = read_stats(out)
    assert stats["frames"]["unreadable"] == 3
    poses = read_tum(out / "trajectory_odometry.tum")
    assert len(poses) == 9 and not {round(stamps[i], 4) for i in (7, 8, 9)} & {round(t, 4) for t, _ in poses}


def test_ground_truth_odometry_without_ground_truth_fails_before_the_run(
    bonn_dir: Path, tmp_path: Path, semmap_run
) -> None:
    data = _tum_subset(bonn_dir, tmp_path / "nogt", 3, gt=False)
    t0 = time.monotonic()
    result = semmap_run([str(data), "--out", str(tmp_path / "run"), "--odometry", "gt", "--no-viz"])
    assert result.returncode == 2
    assert "no ground-truth poses" in result.stderr and "--odometry rgbd" in result.stderr
    assert time.monotonic() - t0 < 20 and not (tmp_path / "run" / "logs").exists()  # nothing was started


@pytest.mark.needs_model
def test_rgbd_odometry_waits_for_each_frames_dynamic_boxes(
    bonn_dir: Path, tmp_path: Path, semmap_run, read_stats
) -> None:
    data = _tum_subset(bonn_dir, tmp_path / "crowd", 20)
    out = tmp_path / "run"
    result = semmap_run(
        [
            str(data),
            "--out",
            str(out),
            "--odometry",
            "rgbd",
            "--lockstep",
            "--only",
            "detector,tracker,odometry",
            "--no-viz",
        ]
    )
    assert result.returncode == 0, result.stderr[-3000:]
    counters = {s["service"]: s["counters"] for s in read_stats(out)["services"].values()}
    assert counters["tracker"]["dynamic_boxes"] > 0  # people in view
    odometry = counters["odometry"]
    assert odometry["poses_published"] == 20
    assert odometry["frames_with_dynamic_boxes"] > 0
    assert "dynamic_from_earlier_frame" not in odometry and "dynamic_wait_timeouts" not in odometry
