"""A dataset with unreadable frames (a corrupt JPEG mid-sequence, a pose file of NaNs, a depth PNG of garbage
bytes, a truncated depth PNG as the last frame): the player counts and announces each, every service skips it,
the lockstep run completes (exit 0, its map and its ground truth without those frames) instead of waiting for a
frame that never comes, and the summary names the skipped frames."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from semmap.datasets.trajectory_io import read_tum

PROJECT = Path(__file__).resolve().parents[2]
FRAMES = 40


@pytest.mark.needs_data
def test_unreadable_frames_are_counted_and_skipped(tmp_path: Path, kitchen_dir: Path, semmap_run,  # noqa: ANN001
                                                   read_stats) -> None:  # noqa: ANN001
    src, seq = kitchen_dir, tmp_path / "seq"
    seq.mkdir()
    shutil.copy(src / "camera-intrinsics.txt", seq)
    for i in range(FRAMES):
        for suffix in ("color.jpg", "depth.png", "pose.txt"):
            shutil.copy(src / f"frame-{i:06d}.{suffix}", seq)
    (seq / "frame-000012.color.jpg").write_bytes(b"\xff\xd8\xff\xe0 not a jpeg")
    (seq / "frame-000020.pose.txt").write_text("nan " * 16)
    (seq / "frame-000025.depth.png").write_bytes(bytes(range(256)) * 40)
    png = (seq / f"frame-{FRAMES - 1:06d}.depth.png").read_bytes()
    (seq / f"frame-{FRAMES - 1:06d}.depth.png").write_bytes(png[: len(png) // 2])
    bad = (12, 20, 25, FRAMES - 1)
    out = tmp_path / "out"
    result = semmap_run([str(seq), "--out", str(out), "--odometry", "gt", "--lockstep", "--no-viz"])
    assert result.returncode == 0, result.stderr[-3000:]
    stats = read_stats(out)
    assert stats["outcome"] == "completed" and stats["frames"]["unreadable"] == len(bad)
    assert stats["frames"]["published"] == FRAMES - len(bad)
    assert stats["frames"]["dropped"] == 0  # an unreadable frame is skipped, not dropped by the detector
    assert stats["services"]["player"]["counters"]["frames_unreadable"] == len(bad)
    for name in ("tracker", "associator", "backend"):
        assert stats["services"][name]["counters"].get("unreadable_skipped") == len(bad), name
        assert stats["services"][name]["state"] == "finished", name
    assert [s["frame"] for s in stats["frames"]["skipped"]] == list(bad)
    assert "frame-000020.pose.txt are not finite" in stats["frames"]["skipped"][1]["reason"]
    stamps = [round(t * 30) for t, _ in read_tum(out / "trajectory_optimized.tum")]
    assert stamps == [i for i in range(FRAMES) if i not in bad]
    gt_stamps = [round(t * 30) for t, _ in read_tum(out / "groundtruth.tum")]
    assert gt_stamps == [i for i in range(FRAMES) if i != 20]  # only the unreadable pose is missing
    assert (out / "map.json").is_file()
    for i in bad:  # the summary names every skipped frame
        assert f"frame {i}: " in result.stdout, result.stdout
    # simulated odometry is said out loud, at the start (even with --quiet) and at the end; the ATE line says
    # how many landmark observations the backend got
    assert "odometry gt: simulated odometry (from ground truth)" in result.stderr, result.stderr
    assert "camera: " in result.stderr and "camera-intrinsics.txt" in result.stderr
    assert "gt: simulated odometry (from ground truth)" in result.stdout
    assert re.search(r"ATE .*(from \d+ landmark observations|the backend received no landmark observations)",
                     result.stdout), result.stdout
    assert stats["odometry"] == {"mode": "gt", "simulated": True}
    player_log = (out / "logs" / "player.log").read_text()
    assert "frame 12 skipped" in player_log and "republishing" not in player_log
