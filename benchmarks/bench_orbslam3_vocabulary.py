"""ORB-SLAM3 RGB-D (pyorbslam3 wheel) on a TUM-layout RGB-D folder with a given vocabulary; prints the ATE RMSE.

    python benchmarks/bench_orbslam3_vocabulary.py VOCABULARY [--data ../shared/data/bonn_crowd]
        [--settings ../shared/data/orbslam3/bonn_settings.yaml] [--out trajectory.tum]

Used for docs/ORBSLAM3.md ("Building a vocabulary"): a vocabulary from `semmap models vocabulary` against the shared
one. Every associated rgb/depth pair is tracked with `track_rgbd`, then `shutdown()` and `save_trajectory_tum`
(bundle-adjusted poses). ORB-SLAM3 is not deterministic: run it a few times.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from semmap.algorithms.evaluation import ate_rmse
from semmap.datasets.trajectory_io import read_tum
from semmap.datasets.tum import associate, read_file_list

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("vocabulary", type=Path)
    ap.add_argument("--data", type=Path, default=SHARED / "bonn_crowd")
    ap.add_argument("--settings", type=Path, default=SHARED / "orbslam3" / "bonn_settings.yaml")
    ap.add_argument("--out", type=Path, default=None, help="trajectory file (default: a temporary one)")
    args = ap.parse_args()
    import pyorbslam3

    rgb = read_file_list(args.data / "rgb.txt")
    depth = read_file_list(args.data / "depth.txt")
    pairs = associate([s for s, _ in rgb], [s for s, _ in depth])
    t0 = time.perf_counter()
    slam = pyorbslam3.Slam(str(args.vocabulary), str(args.settings), sensor=pyorbslam3.Sensor.RGBD, use_viewer=False)
    t1 = time.perf_counter()
    states: dict[str, int] = {}
    for i, j in pairs:
        image = cv2.cvtColor(cv2.imread(str(args.data / rgb[i][1][0])), cv2.COLOR_BGR2RGB)
        d = cv2.imread(str(args.data / depth[j][1][0]), cv2.IMREAD_UNCHANGED).astype(np.float32)
        state = str(slam.track_rgbd(image, d, rgb[i][0]).state).rsplit(".", 1)[-1]
        states[state] = states.get(state, 0) + 1
    t2 = time.perf_counter()
    slam.shutdown()
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp) / "trajectory.tum"
        slam.save_trajectory_tum(str(out))
        ate = ate_rmse(read_tum(args.data / "groundtruth.txt"), read_tum(out))
    print(f"{args.vocabulary}: {len(pairs)} frames, load {t1 - t0:.1f} s, track {t2 - t1:.1f} s, states {states}, "
          f"ATE {ate:.3f} m")  # fmt: skip


if __name__ == "__main__":
    main()
