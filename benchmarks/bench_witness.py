"""What a checked step costs and what it repairs, per witness: the RGB-D registration at full and half size, and the
fit to the static ORB matches alone (`odometry.registration_resolution`, `odometry.repair_witness`).

    python benchmarks/bench_witness.py [--frames 120:170] [--ate-runs 0]

1. Cost: over the Bonn crowd frames given (people walking), each witness measures every consecutive pair as the
   repair does (`PairRegistration.register`; `StepArbiter.sparse_step`, its features computed once a frame, as a
   judgement would need them anyway); printed: median ms a pair, on this machine (name it with `lscpu`).
2. `--ate-runs N`: N lockstep runs of the whole recording with ORB-SLAM3 live per witness (the in-process driver,
   `--set odometry.registration_resolution=... --set odometry.repair_witness=...`): the SLAM alone's ATE and the
   final one, each run (ORB-SLAM3 is not deterministic). About 30 s a run.
Needs ../shared/data (or $SEMMAP_DATA); the ATE runs need the pyorbslam3 wheel and a vocabulary in the model dir.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from semmap.algorithms.odometry.arbiter import StepArbiter  # noqa: E402
from semmap.algorithms.odometry.base import OdometryInput  # noqa: E402
from semmap.algorithms.odometry.registration import PairRegistration  # noqa: E402
from semmap.datasets import find_data_root, open_dataset  # noqa: E402
from semmap.runtime.models.model_store import default_vocabulary  # noqa: E402

WITNESSES = {  # name -> (the registration's downscale, None: the static matches alone; the settings a run takes)
    "dense, full size": (1, ["odometry.registration_resolution=full", "odometry.repair_witness=dense"]),
    "dense, half size": (2, ["odometry.registration_resolution=half", "odometry.repair_witness=dense"]),
    "sparse": (None, ["odometry.repair_witness=sparse"]),
}


def cost_ms(data: Path, first: int, last: int) -> dict[str, float]:
    """Median ms a frame pair per witness, over frames first..last-1."""
    ds = open_dataset(str(data))
    frames = [ds[i] for i in range(first, min(last, len(ds)))]
    times: dict[str, list[float]] = {name: [] for name in WITNESSES}
    for name, (scale, _) in WITNESSES.items():
        registration = PairRegistration("range", scale) if scale is not None else None
        arbiter = StepArbiter()
        for i, f in enumerate(frames):
            k = np.asarray(f.intrinsics.matrix, float)
            t0 = time.perf_counter()
            if registration is not None:
                registration.register(OdometryInput(i, f.stamp, None, f.rgb, f.depth, f.depth_scale, k, []))
            else:
                arbiter.push(i, f.rgb, f.depth, f.depth_scale, k, [])
                arbiter.sparse_step()
            if i > 0:  # (the first frame has no pair)
                times[name].append((time.perf_counter() - t0) * 1e3)
    return {name: round(statistics.median(v), 1) for name, v in times.items()}


def ate_runs(data: Path, runs: int, vocabulary: Path) -> dict[str, list[tuple[float, float]]]:
    """Per witness, (SLAM alone, final) ATE of `runs` lockstep runs of the recording."""
    out: dict[str, list[tuple[float, float]]] = {}
    for name, (_, sets) in WITNESSES.items():
        for _ in range(runs):
            with tempfile.TemporaryDirectory(prefix="semmap-witness-") as tmp:
                summary = Path(tmp) / "summary.json"
                cmd = [sys.executable, "-m", "semmap.runtime.pipeline.inprocess", str(data), "--odometry", "orbslam3",
                       "--json-out", str(summary), "--set", f"odometry.orbslam3_vocabulary={vocabulary}",
                       *[a for s in sets for a in ("--set", s)]]
                proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
                if proc.returncode != 0:
                    raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-2000:]}")
                result = json.loads(summary.read_text())
                result = result[0] if isinstance(result, list) else result
            out.setdefault(name, []).append((round(result["ate_slam_m"], 3), round(result["ate_optimized_m"], 3)))
            print(name, out[name][-1], flush=True)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", default="120:170", help="first:last frame of Bonn crowd timed (people fill the view)")
    ap.add_argument("--ate-runs", type=int, default=0, help="lockstep runs per witness for the ATE (0: none)")
    args = ap.parse_args()
    root = find_data_root()
    if root is None or not (root / "bonn_crowd").is_dir():
        print("skipped: no ../shared/data with bonn_crowd", file=sys.stderr)
        return 0
    data = root / "bonn_crowd"
    first, last = (int(v) for v in args.frames.split(":"))
    costs = cost_ms(data, first, last)
    results = ate_runs(data, args.ate_runs, default_vocabulary() or root / "orbslam3" / "ORBvoc_redkitchen_k10L5.txt") \
        if args.ate_runs > 0 else {}
    print("| witness | ms a frame pair | ATE, SLAM alone -> final (each run) |")
    print("|---|---|---|")
    for name in WITNESSES:
        runs = ", ".join(f"{a:.3f} -> {b:.3f}" for a, b in results.get(name, [])) or "-"
        print(f"| {name} | {costs[name]} | {runs} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
