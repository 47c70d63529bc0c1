"""`semmap view` on a machine without a display says "use --web" in one line instead of the viewer's winit error;
its native viewer's server binds loopback (`--bind 127.0.0.1`, checked in its log)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

PROJECT = Path(__file__).resolve().parents[2]


@pytest.fixture
def rrd(tmp_path: Path) -> Path:
    import rerun as rr

    path = tmp_path / "run.rrd"
    rec = rr.RecordingStream("semmap-test")
    rec.save(str(path))
    rec.log("p", rr.Points3D([[0.0, 0.0, 0.0]]))
    rec.flush()
    return path


def _view(rrd: Path, display: str | None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["CI"] = "true"
    if display is not None:
        env["DISPLAY"] = display
    return subprocess.run([sys.executable, "-m", "semmap.cli", "view", str(rrd)], cwd=PROJECT, capture_output=True,
                          text=True, timeout=60, env=env)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="X11 / Wayland displays")
def test_view_without_a_display_says_use_web(rrd: Path) -> None:
    result = _view(rrd, None)
    assert result.returncode == 2 and "no display" in result.stderr and "--web" in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="X11 / Wayland displays")
def test_view_with_a_dead_display_says_use_web_and_binds_loopback(rrd: Path) -> None:
    if Path("/tmp/.X11-unix/X97").exists():
        pytest.skip("display :97 exists here")
    result = _view(rrd, ":97")  # a DISPLAY with no X server behind it
    assert result.returncode == 2, result.stderr
    assert "winit" not in result.stderr and "error: no display" in result.stderr and "--web" in result.stderr
    if "Listening for gRPC connections" in result.stderr:
        assert "on 127.0.0.1:" in result.stderr and "0.0.0.0" not in result.stderr, result.stderr


def test_the_web_page_gets_the_map_without_the_images(tmp_path: Path) -> None:
    """`semmap view --web` serves a copy without the camera images and their boxes (the bulk of a recording, which
    the page would otherwise stream before the landmarks): the landmarks and trajectories stay, in a fraction of
    the bytes; `--images` serves the whole file."""
    import numpy as np
    import rerun as rr

    from semmap.cli.view import _rerun_executable, map_first_copy

    full = tmp_path / "run.rrd"
    rec = rr.RecordingStream("semmap-test")
    rec.save(str(full))
    noise = np.random.default_rng(0).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    for i in range(20):
        rec.set_time("frame", sequence=i)
        rec.log("world/camera/image", rr.Image(noise))
        rec.log("world/camera/image/detections", rr.Boxes2D(centers=[[10, 10]], half_sizes=[[5, 5]]))
        rec.log("world/camera/depth", rr.DepthImage(noise[..., 0].astype(np.uint16), meter=1000.0))
        rec.log("world/landmarks", rr.Boxes3D(centers=[[0, 0, i * 0.01]], half_sizes=[[0.1, 0.1, 0.1]]))
        rec.log("world/trajectory/odometry", rr.LineStrips3D([[[0, 0, 0], [i, 0, 0]]]))
    rec.flush()
    viewer = _rerun_executable()
    assert viewer is not None
    env = {**os.environ, "CI": "true", "RERUN_ANALYTICS": "0"}
    copy = map_first_copy(viewer, full, tmp_path, env)
    assert copy is not None and copy.stat().st_size < full.stat().st_size / 5
    printed = subprocess.run([viewer, "rrd", "print", str(copy)], capture_output=True, text=True, env=env).stdout
    entities = {line.rsplit(" - ", 2)[1] for line in printed.splitlines() if line.startswith("Chunk(")}
    assert {"/world/landmarks", "/world/trajectory/odometry"} <= entities, entities
    assert not any(e.startswith("/world/camera/image") or e == "/world/camera/depth" for e in entities), entities
