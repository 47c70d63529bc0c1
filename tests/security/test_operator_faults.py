"""Operator faults: each ends with one clear message that names the real cause, a non-zero exit code
where something was lost, no process left behind, and no output file truncated."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import pytest

from semmap.core.messages import ServiceStatus
from semmap.datasets.trajectory_io import read_tum
from semmap.runtime.orchestrator import Orchestrator, RunFailed, RunPlan, ServiceSpec

PROJECT = Path(__file__).resolve().parents[2]


def _leftovers(marker: str) -> list[str]:
    """Processes (other than this one) whose command line names `marker` (every child gets `--out DIR`)."""
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid():
            continue
        with contextlib.suppress(OSError):
            cmdline = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            if marker in cmdline and (proc / "stat").read_text().split()[2] != "Z":
                found.append(f"{proc.name}: {cmdline[:200]}")
    return found


def _assert_no_leftovers(marker: str, within_s: float = 10.0) -> None:
    deadline = time.monotonic() + within_s
    while _leftovers(marker) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert _leftovers(marker) == []


@contextlib.contextmanager
def _tmpfs(path: Path, options: str) -> Iterator[Path]:
    """A small tmpfs at `path` (root only: skips elsewhere) for a read-only or full disk."""
    path.mkdir(parents=True, exist_ok=True)
    result = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)], capture_output=True)
    if result.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {result.stderr.decode(errors='replace').strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


def _popen_run(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "semmap.cli", "run", *args, "--quiet"],
        cwd=PROJECT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "CI": "true"},
    )


def _wait_for_log(path: Path, text: str, timeout: float = 180.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError):
            if text in path.read_text(errors="replace"):
                return
        time.sleep(0.2)
    raise AssertionError(f"{text!r} not in {path} after {timeout:.0f} s")


def _kitchen_copy(kitchen_dir: Path, dest: Path, frames: int, poses: bool = True, depth_8bit: bool = False) -> Path:
    dest.mkdir(parents=True)
    shutil.copy(kitchen_dir / "camera-intrinsics.txt", dest) if (
        kitchen_dir / "camera-intrinsics.txt"
    ).exists() else None
    for i in range(frames):
        stem = f"frame-{i:06d}"
        shutil.copy(kitchen_dir / f"{stem}.color.jpg", dest)
        if depth_8bit:  # what an operator may have: depth saved as 8-bit PNGs
            depth = cv2.imread(str(kitchen_dir / f"{stem}.depth.png"), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(dest / f"{stem}.depth.png"), (depth // 256).astype("uint8"))
        else:
            shutil.copy(kitchen_dir / f"{stem}.depth.png", dest)
        if poses:
            shutil.copy(kitchen_dir / f"{stem}.pose.txt", dest)
    return dest


def _assert_outputs_whole(out: Path) -> None:
    """Every output present parses completely (written to a temporary file and renamed, never in place)."""
    for path in out.glob("*.tum"):
        assert path.stat().st_size > 0, path
        read_tum(path)
    for name in ("map.json", "stats.json"):
        if (out / name).exists():
            json.loads((out / name).read_text())
    assert not list(out.glob("*.tmp")) and not list(out.glob(".*.tmp")), list(out.iterdir())


# -- refused before anything starts ------------------------------------------------------------------------


def test_read_only_out_is_one_clear_error_and_no_process(tmp_path: Path, semmap_run) -> None:  # noqa: ANN001
    with _tmpfs(tmp_path / "ro", "ro,size=1m") as ro:
        for out in (ro, ro / "run"):  # the directory itself, or one to create in it
            result = semmap_run(["synthetic:frames=10", "--out", str(out), "--no-viz"], timeout=60)
            assert result.returncode == 2, result.stderr
            assert "Read-only file system" in result.stderr and "Traceback" not in result.stderr, result.stderr
            assert result.stderr.count("error:") == 1
            _assert_no_leftovers(str(out))


def test_config_values_out_of_range_are_refused_naming_the_key(semmap_run) -> None:  # noqa: ANN001
    for item, key in (
        ("detector.confidence=-1", "detector.confidence"),
        ("detector.confidence=1.5", "detector.confidence"),
        ("associator.gate_u=0", "associator.gate_u"),
    ):
        result = semmap_run(["synthetic:frames=5", "--set", item], timeout=60)
        assert result.returncode == 2 and key in result.stderr, (item, result.stderr)


def test_a_non_empty_out_needs_resume_or_overwrite(tmp_path: Path, semmap_run) -> None:  # noqa: ANN001
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("not semmap's")
    result = semmap_run(["synthetic:frames=5", "--out", str(mine)], timeout=60)
    assert result.returncode == 2 and "is not empty" in result.stderr and "--overwrite" in result.stderr
    result = semmap_run(["synthetic:frames=5", "--out", str(mine), "--overwrite"], timeout=60)
    assert result.returncode == 2 and "does not look like a semmap output directory" in result.stderr
    assert (mine / "notes.txt").read_text() == "not semmap's"


@pytest.mark.needs_data
def test_a_dataset_whose_frames_cannot_be_read_is_refused(
    tmp_path: Path,
    kitchen_dir: Path,  # noqa: ANN001
    semmap_run,
) -> None:  # noqa: ANN001
    data = _kitchen_copy(kitchen_dir, tmp_path / "eight-bit", 3, depth_8bit=True)
    out = tmp_path / "out"
    result = semmap_run([str(data), "--out", str(out), "--no-viz"], timeout=120)
    assert result.returncode == 2 and "first frame cannot be read" in result.stderr, result.stderr
    assert "depth" in result.stderr
    _assert_no_leftovers(str(out))


@pytest.mark.needs_data
def test_gt_odometry_without_ground_truth_is_refused_at_once(
    tmp_path: Path,
    kitchen_dir: Path,  # noqa: ANN001
    semmap_run,
) -> None:  # noqa: ANN001
    data = _kitchen_copy(kitchen_dir, tmp_path / "no-poses", 3, poses=False)
    started = time.monotonic()
    result = semmap_run([str(data), "--out", str(tmp_path / "out"), "--odometry", "gt", "--no-viz"], timeout=120)
    assert result.returncode == 2 and "needs ground-truth poses" in result.stderr, result.stderr
    assert time.monotonic() - started < 30


def test_overwrite_replaces_a_previous_run(tmp_path: Path, semmap_run) -> None:  # noqa: ANN001
    out = tmp_path / "run"
    (out / "logs").mkdir(parents=True)
    (out / "stats.json").write_text("{}")
    result = semmap_run(
        ["synthetic:frames=5", "--out", str(out), "--overwrite", "--no-viz", "--set", "run.min_free_mb=1e12"],
        timeout=60,
    )  # refused after the overwrite, before a run
    assert result.returncode == 2 and "MB free" in result.stderr, result.stderr
    assert not (out / "stats.json").exists() and not (out / "logs").exists()


# -- while running -----------------------------------------------------------------------------------------


def test_two_runs_with_one_out_the_second_is_refused(tmp_path: Path, semmap_run) -> None:  # noqa: ANN001
    out = tmp_path / "run"
    first = _popen_run(["synthetic:frames=2000", "--out", str(out), "--no-viz"])
    try:
        _wait_for_log(out / "logs" / "player.log", "started as")
        second = semmap_run(["synthetic:frames=5", "--out", str(out), "--overwrite", "--no-viz"], timeout=60)
        assert second.returncode == 2 and "in use by another semmap run" in second.stderr, second.stderr
        assert f"pid {first.pid}" in second.stderr
        assert (out / "logs" / "player.log").is_file()  # the first run's files are untouched
    finally:
        first.send_signal(signal.SIGINT)
        first.communicate(timeout=60)
    assert first.returncode == 130
    _assert_no_leftovers(str(out))
    _assert_outputs_whole(out)


def test_a_service_that_stops_unasked_fails_the_run(tmp_path: Path) -> None:
    """A child leaving with exit 0 "stopped" (what a forged `stop` used to cause) is a failure, not a hang."""
    out = tmp_path / "run"
    run = _popen_run(["synthetic:frames=2000", "--out", str(out), "--no-viz"])
    _wait_for_log(out / "logs" / "tracker.log", "started as")
    _wait_for_log(out / "logs" / "player.log", "pipeline ready")
    tracker = next(
        int(p.name)
        for p in Path("/proc").iterdir()
        if p.name.isdigit()
        and str(out) in (p / "cmdline").read_bytes().decode(errors="replace")
        and b"semmap.services.tracker" in (p / "cmdline").read_bytes()
    )
    os.kill(tracker, signal.SIGTERM)  # it writes its outputs and says "stopped", exit 0: nobody asked it to
    _, err = run.communicate(timeout=120)
    assert run.returncode == 1, err[-3000:]
    assert "tracker stopped unasked (exit 0, stopped)" in err
    _assert_no_leftovers(str(out))
    stats = json.loads((out / "stats.json").read_text())
    assert stats["outcome"] == "failed" and "tracker stopped unasked" in stats["failure"]


def test_sigterm_ends_the_run_and_every_service_within_seconds(tmp_path: Path) -> None:
    out = tmp_path / "run"
    run = _popen_run(["synthetic:frames=2000", "--out", str(out), "--no-viz"])
    _wait_for_log(out / "logs" / "player.log", "pipeline ready")
    time.sleep(2)
    started = time.monotonic()
    run.send_signal(signal.SIGTERM)
    run.communicate(timeout=60)
    assert time.monotonic() - started < 30
    assert run.returncode == 130
    _assert_no_leftovers(str(out))
    _assert_outputs_whole(out)


def test_the_deadline_fails_a_run_that_takes_too_long(tmp_path: Path, semmap_run) -> None:  # noqa: ANN001
    result = semmap_run(
        ["synthetic:frames=2000", "--out", str(tmp_path / "run"), "--no-viz", "--deadline", "20"], timeout=180
    )
    assert result.returncode == 1 and "deadline of 20 s" in result.stderr, result.stderr[-2000:]
    _assert_no_leftovers(str(tmp_path / "run"))


def test_a_full_disk_names_the_cause_and_truncates_nothing(tmp_path: Path, semmap_run) -> None:  # noqa: ANN001
    with _tmpfs(tmp_path / "small", "size=4m") as disk:
        out = disk / "run"
        # leave ~700 KB: enough to start, not for the journals of a 60-frame run (depth clouds of keyframes)
        filler = disk / "filler"
        free = shutil.disk_usage(disk).free
        filler.write_bytes(b"\0" * (free - 700_000))
        result = semmap_run(
            ["synthetic:frames=60", "--out", str(out), "--no-viz", "--set", "run.min_free_mb=0.1"], timeout=300
        )
        assert result.returncode != 0, result.stderr[-3000:]
        assert "No space left on device" in result.stderr or "disk is full" in result.stderr, result.stderr[-3000:]
        assert "no progress" not in result.stderr.split("\n---")[0]
        _assert_no_leftovers(str(out))
        _assert_outputs_whole(out)


# -- the orchestrator's frame accounting ---------------------------------------------------------------------


def _orchestrator(tmp_path: Path) -> Orchestrator:
    return Orchestrator(
        RunPlan("data", tmp_path, "robot1", "lockstep", [ServiceSpec("detector"), ServiceSpec("tracker")])
    )


def test_fewer_frames_processed_than_sent_or_none_fail_the_run(tmp_path: Path) -> None:
    orch = _orchestrator(tmp_path)
    player = ServiceStatus("robot1", "player", "player", "finished", 59, {"frames_published": 60, "frames_total": 60})
    orch.statuses["player"] = player
    orch.progress = {"detector": 59, "tracker": 40}
    with pytest.raises(RunFailed, match="only 41 of the 60 frames"):
        orch._check_frames()
    orch.progress["tracker"] = 59
    orch._check_frames()  # all there
    orch.statuses["player"] = ServiceStatus(
        "robot1", "player", "player", "finished", -1, {"frames_unreadable": 12, "frames_total": 12}
    )
    orch.progress = {}
    with pytest.raises(RunFailed, match="all 12 frames of data were unreadable"):
        orch._check_frames()


# -- a finished run is left alone, a killed run leaves no process --------------------------------------------


def _tree_digest(folder: Path) -> dict[str, tuple[str, int]]:
    """Every file under `folder` (hidden ones included) by relative path: its SHA-256 and its mode."""
    import hashlib

    return {str(p.relative_to(folder)): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mode)
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_resume_of_a_completed_run_says_so_and_changes_nothing(tmp_path: Path, semmap_run) -> None:  # noqa: ANN001
    out = tmp_path / "run"
    first = semmap_run(["synthetic:frames=6", "--out", str(out), "--no-viz"], timeout=180)
    assert first.returncode == 0, first.stderr[-3000:]
    before = _tree_digest(out)
    assert "stats.json" in before and ".semmap.lock" in before
    started = time.monotonic()
    again = semmap_run(["synthetic:frames=6", "--out", str(out), "--no-viz", "--resume"], timeout=60)
    took = time.monotonic() - started
    assert again.returncode == 2 and "holds a completed run" in again.stderr, again.stderr
    assert len(again.stderr.strip().splitlines()) == 1, again.stderr
    assert took < 10, took
    assert _tree_digest(out) == before


def test_sigkill_of_the_run_leaves_no_service_behind(tmp_path: Path) -> None:
    """The run's children stop when it is killed with SIGKILL (no handler of its own runs): PR_SET_PDEATHSIG and
    a parent watch in each service; the folder's lock is held by the children until the last one is gone."""
    from semmap.core.outputs import OutputError, OutputLock

    out = tmp_path / "run"
    run = _popen_run(["synthetic:frames=2000", "--out", str(out), "--no-viz"])
    _wait_for_log(out / "logs" / "player.log", "pipeline ready")
    time.sleep(1)
    assert len(_leftovers(str(out))) >= 7  # the run and its services (player, odometry, detector, ...)
    run.send_signal(signal.SIGKILL)
    run.communicate(timeout=30)
    children = [p for p in _leftovers(str(out)) if "semmap.services" in p]
    lock = OutputLock(out)
    if children:  # (they may all have gone already on a quiet machine) while they live, the folder is theirs
        with contextlib.suppress(OutputError):
            lock.acquire()
            still = [p for p in _leftovers(str(out)) if "semmap.services" in p]
            lock.release()
            assert not still, f"lock acquired while services live: {still}"
    _assert_no_leftovers(str(out), within_s=10.0)
    # and once they are gone, it is free: a process that is exiting has already lost its command line (so it is no
    # leftover) but closes its files, the lock among them, a moment later (seen once under the full suite's load)
    deadline = time.monotonic() + 5.0
    while True:
        try:
            lock.acquire()
            break
        except OutputError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)
    lock.release()


def test_a_class_the_detector_does_not_know_is_refused_naming_the_known_ones(tmp_path: Path, semmap_run) -> None:  # noqa: ANN001
    out = tmp_path / "run"
    result = semmap_run(["synthetic:frames=3", "--out", str(out), "--no-viz", "--set", "detector.classes=unicorn,cup"],
                        timeout=60)
    assert result.returncode == 2, result.stderr
    line = result.stderr.strip()
    assert line.startswith("error: detector.classes: 'unicorn' not among the classes") and "\n" not in line
    assert "cup" in line and "chair" in line  # the known ones, listed
    assert not out.exists()


@pytest.mark.needs_data
@pytest.mark.needs_model
def test_a_class_the_model_does_not_know_is_refused_before_any_service(tmp_path: Path, kitchen_dir: Path,  # noqa: ANN001
                                                                       semmap_run) -> None:  # noqa: ANN001
    result = semmap_run([str(kitchen_dir), "--out", str(tmp_path / "run"), "--no-viz", "--set",
                         "detector.exclude=unicorn"], timeout=60)
    assert result.returncode == 2 and "detector.exclude: 'unicorn' not among the classes the model" in result.stderr
    assert "person, bicycle" in result.stderr and not (tmp_path / "run").exists()
