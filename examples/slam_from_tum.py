"""Drive semmap like an external SLAM would: frames from a dataset, poses from a TUM trajectory file.

    semmap run external --out out/ext &            # the pipeline, waiting for a SLAM
    python examples/slam_from_tum.py DATASET TRAJECTORY.tum --connect tcp/127.0.0.1:7447

A real SLAM publishes its own images and its own poses; here the dataset stands in for the camera and the
trajectory file for the SLAM's estimate. Lockstep: each frame waits until semmap has processed it, so the map
is the same as `semmap run DATASET --odometry file:TRAJECTORY.tum`.

It also subscribes to semmap's dynamic objects (`semmap/v1/<robot>/dynamic`: per frame, the boxes of people,
animals and things seen moving, each with a depth range): a dynamic SLAM would leave the features or depth inside
them out of its tracking (see `masked_depth`); here they are counted and the share of depth they cover reported.
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from semmap.core.messages import DynamicObjects, GroundTruthInstance, Intrinsics
from semmap.datasets import open_dataset
from semmap.datasets.trajectory_io import read_tum
from semmap.runtime.client import SemmapClient


def masked_depth(depth: np.ndarray, dynamic: DynamicObjects, depth_scale: float) -> np.ndarray:
    """What a SLAM would track on: the depth with the pixels of dynamic objects (within each box, those in the
    box's depth range; the whole box when it has none) set to 0."""
    out = depth.copy()
    for b in dynamic.boxes:
        x0, y0, x1, y1 = (int(round(v)) for v in b.box)
        patch = out[max(0, y0):y1, max(0, x0):x1]
        if b.depth_max_m <= 0:
            patch[:] = 0
        else:
            z = patch * depth_scale
            patch[(z >= b.depth_min_m) & (z <= b.depth_max_m)] = 0
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", help="dataset path or 'synthetic[:...]' (the camera)")
    parser.add_argument("trajectory", help="TUM trajectory (the SLAM's poses)")
    parser.add_argument("--connect", default=None, help="semmap's Zenoh endpoint (default tcp/127.0.0.1:7447)")
    parser.add_argument("--robot", default="robot1")
    parser.add_argument("--max-frames", type=int, default=0)
    parser.add_argument("--sigma-translation", type=float, default=0.01, help="per-frame, metres")
    parser.add_argument("--sigma-rotation-deg", type=float, default=0.5, help="per-frame, degrees")
    args = parser.parse_args(argv)

    dataset = open_dataset(args.dataset)
    poses = read_tum(args.trajectory)
    stamps = np.array([t for t, _ in poses])
    total = min(len(dataset), args.max_frames) if args.max_frames > 0 else len(dataset)
    dynamic: dict[int, DynamicObjects] = {}
    with SemmapClient(args.robot, args.connect or "tcp/127.0.0.1:7447") as client:
        client.on_dynamic(lambda m: dynamic.__setitem__(m.frame_id, m))  # (a Zenoh thread: keep it short)
        client.wait_ready()
        masked = 0.0
        for i in range(total):
            frame = dataset[i]
            k = frame.intrinsics
            instances = [GroundTruthInstance(x.instance_id, x.class_name, tuple(x.box), x.visible_pixels, x.moving)
                         for x in frame.instances]
            client.publish_frame(i, frame.stamp, frame.rgb, frame.depth, frame.depth_scale,
                                 Intrinsics(k.fx, k.fy, k.cx, k.cy, k.width, k.height), instances)
            pose = poses[int(np.argmin(np.abs(stamps - frame.stamp)))][1]
            client.publish_pose(i, frame.stamp, pose, sigma_translation=args.sigma_translation,
                                sigma_rotation=math.radians(args.sigma_rotation_deg))
            client.wait_frame_done(i)
            if i in dynamic:  # lockstep: the tracker answered frame i before the pipeline finished it
                valid = np.count_nonzero(frame.depth)
                kept = np.count_nonzero(masked_depth(frame.depth, dynamic[i], frame.depth_scale))
                masked += (valid - kept) / max(valid, 1)
        client.end_of_stream(total - 1, total)
        corrected = client.corrected_trajectory()
        print(f"sent {total} frames; backend corrected {len(corrected)} poses", file=sys.stderr)
        boxes = sum(len(m.boxes) for m in dynamic.values())
        print(f"dynamic objects: {len(dynamic)} frames, {boxes} boxes, {100 * masked / max(total, 1):.1f} % of the "
              f"depth on average", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
