"""`semmap-client` (clients/python): semmap.runtime.client, .core.messages and .core.keys on Python 3.10 (ROS 2 Humble)
and 3.12 (Jazzy), without the heavy stack, talking to the real bus.

Each interpreter found (on PATH as python3.X, or pyenv's ~/.pyenv/versions/3.X.*; Debian 12 ships only 3.11,
so a machine without pyenv tests on 3.11 alone and says so in the skip reasons) gets a bare venv, `pip install
clients/python` (its loose pins resolve from PyPI for that interpreter), and runs a script that imports the client,
checks that no heavy package is installed or imported, and publishes a frame and a pose through a router that this
test process (the full stack, Python 3.11) holds; the test decodes both with the services' own message classes.
"""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from semmap.core.messages import Frame, OdometryPose
from semmap.runtime.transport.bus import Bus, BusConfig

PROJECT = Path(__file__).resolve().parents[2]
HEAVY = ("open3d", "gtsam", "onnxruntime", "rerun", "evo", "scipy", "yaml")

CLIENT_SCRIPT = r"""
import importlib.util, sys
import numpy as np
from semmap.runtime.client import SemmapClient
from semmap.core.messages import Intrinsics
heavy = [m for m in sys.argv[3].split(",") if importlib.util.find_spec(m) is not None or m in sys.modules]
assert not heavy, f"heavy packages present: {heavy}"
rgb = np.zeros((48, 64, 3), np.uint8); rgb[10:20, 10:30] = (200, 40, 40)
depth = np.full((48, 64), 1500, np.uint16)
pose = np.eye(4); pose[:3, 3] = (1.0, 2.0, 3.0)
with SemmapClient(robot="lightbot", connect=sys.argv[1]) as client:
    for i in range(int(sys.argv[2])):
        client.publish_frame(i, i / 30, rgb, depth, 0.001, Intrinsics(60.0, 60.0, 32.0, 24.0, 64, 48))
        client.publish_pose(i, i / 30, pose)
print("python", sys.version.split()[0], "ok")
"""


def _interpreter(version: str) -> str | None:
    """pyenv's build of that version, else python3.X on PATH if it runs (pyenv's shims exist but may refuse)."""
    pyenv = sorted(glob.glob(os.path.expanduser(f"~/.pyenv/versions/{version}.*/bin/python{version}")))
    candidates = [*pyenv[-1:], shutil.which(f"python{version}")]
    for python in filter(None, candidates):
        if subprocess.run([python, "-c", "pass"], capture_output=True, timeout=60).returncode == 0:
            return python
    return None


@pytest.mark.slow
@pytest.mark.parametrize("version", ["3.10", "3.11", "3.12"])
def test_light_client_installs_without_the_heavy_stack_and_talks_to_the_bus(
    version: str, tmp_path: Path, router
) -> None:
    python = _interpreter(version)
    if python is None:
        pytest.skip(f"no Python {version} here (Debian 12 has only 3.11; pyenv or deadsnakes provide the others)")
    venv = tmp_path / "venv"
    subprocess.run([python, "-m", "venv", str(venv)], check=True, timeout=600)
    pip = subprocess.run(
        [str(venv / "bin" / "python"), "-m", "pip", "install", "-q", str(PROJECT / "clients" / "python")],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert pip.returncode == 0, pip.stderr[-3000:]
    frames, poses, done = [], [], threading.Event()
    bus = Bus(BusConfig(mode="client", connect=[router.endpoint], listen=[]), "lightbot")
    try:
        bus.subscribe(bus.keys.frames, Frame, frames.append)
        bus.subscribe(bus.keys.odometry, OdometryPose, lambda p: (poses.append(p), done.set()))
        # a few frames: the first may go out before the router has propagated the subscription
        run = subprocess.run(
            [str(venv / "bin" / "python"), "-c", CLIENT_SCRIPT, router.endpoint, "20", ",".join(HEAVY)],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=tmp_path,
        )
        assert run.returncode == 0, run.stderr[-3000:]
        assert f"python {version}" in run.stdout
        assert done.wait(10)
    finally:
        bus.close()
    assert frames and poses
    frame, pose = frames[-1], poses[-1]
    assert frame.rgb().shape == (48, 64, 3) and int(frame.depth()[5, 5]) == 1500
    np.testing.assert_allclose(pose.pose[:3, 3], (1.0, 2.0, 3.0))
    assert sys.version_info[:2] == (3, 11)  # the services' side of the wire
