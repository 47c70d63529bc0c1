"""`semmap view` on a machine without a display says "use --web" in one line instead of the viewer's winit error
(issue 30); its native viewer's server binds loopback (`--bind 127.0.0.1`, checked in its log)."""

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
