"""A process that used Open3D ends with status 0 even where Python never frees what it held.

Open3D counts its own allocations and, when the process ends with one still alive, prints "Memory Statistics" and
ends the process with status 1 (its leak check, meant for its unit tests). A service's objects are not always freed
before that check runs: a thread still holding them when the interpreter stops keeps them alive. A player that
stopped cleanly could still report failure now and then (tests/reliability/test_startup_and_router_restart.py)
while the synthetic scene kept its triangles as an Open3D tensor, so it keeps numpy arrays, wrapped for Open3D
per cast. This pins the scene, and the `rgbd` odometry with a previous frame (Open3D images that wrap numpy
memory), in a thread the interpreter never finishes, so the check runs with them alive every time.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

PROJECT = Path(__file__).resolve().parents[2]

SCRIPT = textwrap.dedent("""
    import threading, time
    from semmap.algorithms.odometry.frontends import OdometryInput, make_frontend
    from semmap.core.config import load_config
    from semmap.datasets import open_dataset

    scene = open_dataset("synthetic:frames=4,width=160,height=120")
    frames = [scene[i] for i in range(3)]
    odometry = make_frontend("rgbd", load_config().odometry)
    for i, f in enumerate(frames):
        odometry.estimate(OdometryInput(i, f.stamp, f.gt_pose, f.rgb, f.depth, f.depth_scale, f.intrinsics.matrix))
    assert odometry.registration.has_previous
    # held by a thread that is still running when the interpreter stops: never freed before Open3D's check
    threading.Thread(target=lambda held=(scene, odometry): time.sleep(60), daemon=True).start()
    print("done", flush=True)
""")


def test_a_process_holding_the_synthetic_scene_and_rgbd_odometry_at_exit_ends_with_status_0() -> None:
    run = subprocess.run([sys.executable, "-c", SCRIPT], cwd=PROJECT, capture_output=True, text=True, timeout=120)
    assert "done" in run.stdout, run.stderr[-3000:]
    assert "Memory Statistics" not in run.stdout + run.stderr, run.stdout[-3000:] + run.stderr[-3000:]
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
