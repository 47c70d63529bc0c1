"""What the viewer logs to draw the odometry path, over a run of N frames: MB sent to Rerun and CPU a frame.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_viewer_paths.py [--frames 10000]

`semmap` is imported from PYTHONPATH, so the same script measures another checkout's viewer
(`PYTHONPATH=../other-checkout python benchmarks/bench_viewer_paths.py`). The viewer's odometry handler is fed one
pose per frame (a straight line, 1 cm a frame) into a Rerun memory recording, drained every 100 frames. Why: a
camera path re-logged whole at every redraw costs O(frames) each time, so the recording grows with the square of
the run's length; drawn in parts (`PathParts`), it grows with the length.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import rerun as rr

from semmap.core.messages import OdometryPose
from semmap.runtime.transport.service import common_arguments
from semmap.services.viz import service as viz_service


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=10_000)
    args = ap.parse_args()
    parser = argparse.ArgumentParser()
    common_arguments(parser)
    viz = viz_service.VizService(parser.parse_args(["--mode", "realtime"]))
    rr.init("semmap-bench-viewer-paths", spawn=False)
    recording = rr.memory_recording()
    viz.rr, viz.correction, viz.up, viz.odometry = rr, None, np.array([0.0, -1.0, 0.0]), {}
    if hasattr(viz_service, "PathParts"):  # (a checkout from before the paths were drawn in parts has none)
        viz.odometry_path = viz_service.PathParts()
    pose = np.eye(4)
    logged = 0
    started = time.process_time()
    for frame_id in range(args.frames):
        pose[0, 3] = frame_id * 0.01
        viz.on_odometry(OdometryPose("bench", frame_id, frame_id / 30, pose.copy()))
        if frame_id % 100 == 0:
            logged += len(recording.drain_as_bytes())
    logged += len(recording.drain_as_bytes())
    cpu_ms = (time.process_time() - started) / args.frames * 1e3
    print(f"odometry path, {args.frames} frames: {logged / 1e6:.1f} MB logged, {cpu_ms:.2f} ms CPU a frame")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
