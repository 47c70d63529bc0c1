"""A dataset with unreadable frames (a corrupt JPEG mid-sequence, a truncated depth PNG as the last frame):
the player counts and announces each, every service skips it, and the lockstep run completes instead of
waiting for a frame that never comes."""

from __future__ import annotations

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
    png = (seq / f"frame-{FRAMES - 1:06d}.depth.png").read_bytes()
    (seq / f"frame-{FRAMES - 1:06d}.depth.png").write_bytes(png[: len(png) // 2])
    out = tmp_path / "out"
    result = semmap_run([str(seq), "--out", str(out), "--odometry", "gt", "--lockstep", "--no-viz"])
    assert result.returncode == 0, result.stderr[-3000:]
    stats = read_stats(out)
    assert stats["outcome"] == "completed" and stats["frames"]["unreadable"] == 2
    assert stats["frames"]["published"] == FRAMES - 2
    assert stats["services"]["player"]["counters"]["frames_unreadable"] == 2
    for name in ("tracker", "associator", "backend"):
        assert stats["services"][name]["counters"].get("unreadable_skipped") == 2, name
        assert stats["services"][name]["state"] == "finished", name
    stamps = [round(t * 30) for t, _ in read_tum(out / "trajectory_optimized.tum")]
    assert stamps == [i for i in range(FRAMES) if i not in (12, FRAMES - 1)]
    player_log = (out / "logs" / "player.log").read_text()
    assert "frame 12 skipped" in player_log and "republishing" not in player_log
