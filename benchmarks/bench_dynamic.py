"""Dynamic scenes on a real recording: Bonn RGB-D Dynamic "crowd" (people walking, the camera following them).

    python benchmarks/bench_dynamic.py [--data DIR] [--out-root DIR] [--only NAMES] [--keep] [--max-frames N]

Runs the real pipeline (`semmap run DATA --lockstep --odometry MODE --quiet --no-viz`, every service its own
process over Zenoh, the ONNX YOLOv5s detector) and `semmap eval` on each case:

  rgbd-nomask   `--odometry rgbd --only odometry` with `odometry.dynamic_mask=none`: the front end alone on the
                raw depth (what the people do to it; no detector, no backend)
  rgbd          `--odometry rgbd`: the depth inside the tracker's dynamic boxes left out (the default)
  gt            `--odometry gt`: ground truth (its 67 ms gap at frame 160 is interpolated)
  rgbd-geometry `rgbd` with `associator.dynamic_classes=[]`: people kept out by the motion tests alone

and prints a row per case: front-end ATE, optimised ATE, landmarks by class, `person` landmarks, landmarks
retired as moved, run time. The targets: rgbd optimised ATE <= 0.10 m and 0 person landmarks; gt
completes with 0 person landmarks. Needs ../shared/data/bonn_crowd (or $SEMMAP_DATA/bonn_crowd) and the
detector model (`semmap models fetch`).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

PROJECT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(PROJECT))
FRONT_END_ONLY = {"rgbd-nomask"}
CASES: dict[str, tuple[str, list[str]]] = {
    "rgbd-nomask": ("rgbd", ["odometry.dynamic_mask=none"]),
    "rgbd": ("rgbd", []),
    "gt": ("gt", []),
    "rgbd-geometry": ("rgbd", ["associator.dynamic_classes=[]"]),
}


def default_data() -> Path:
    root = Path(os.environ.get("SEMMAP_DATA", PROJECT.parent / "shared" / "data"))
    return root / "bonn_crowd"


def run_case(name: str, data: Path, out: Path, max_frames: int | None) -> dict:
    mode, overrides = CASES[name]
    semmap = str(Path(sys.executable).with_name("semmap"))
    cmd = [semmap, "run", str(data), "--out", str(out), "--lockstep", "--odometry", mode, "--quiet", "--no-viz"]
    for item in overrides:
        cmd += ["--set", item]
    if max_frames:
        cmd += ["--max-frames", str(max_frames)]
    if name in FRONT_END_ONLY:
        cmd += ["--only", "odometry"]
    t0 = time.monotonic()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=PROJECT)
    row: dict = {"case": name, "rc": proc.returncode, "seconds": round(time.monotonic() - t0, 1)}
    if proc.returncode != 0:
        row["error"] = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        return row
    if name in FRONT_END_ONLY:
        from semmap.algorithms.evaluation import ate_rmse
        from semmap.datasets.trajectory_io import read_tum

        ate = ate_rmse(read_tum(out / "groundtruth.tum"), read_tum(out / "trajectory_odometry.tum"))
        row.update(ate_frontend_m=ate, ate_optimized_m=float("nan"), landmarks={}, persons=0, retired=0)
        return row
    subprocess.run([semmap, "eval", str(out)], capture_output=True, text=True, cwd=PROJECT, check=True)
    ev = json.loads((out / "eval.json").read_text())
    landmarks = json.loads((out / "map.json").read_text())["landmarks"]
    stats = json.loads((out / "stats.json").read_text())
    counters = {
        k: v
        for s in stats.get("services", {}).values()
        if isinstance(s, dict)
        for k, v in (s.get("counters") or {}).items()
    }
    row.update(
        ate_frontend_m=ev["ate_odometry_m"],
        ate_optimized_m=ev["ate_optimized_m"],
        landmarks=dict(sorted(Counter(lm["class"] for lm in landmarks).items())),
        persons=sum(lm["class"] == "person" for lm in landmarks),
        retired=counters.get("landmarks_retired_moving", 0),
        dynamic_boxes=counters.get("dynamic_boxes", 0),
    )
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=default_data())
    parser.add_argument("--out-root", type=Path, default=None, help="keep the runs here (default: a temp dir)")
    parser.add_argument("--only", default=",".join(CASES), help=f"comma-separated cases of {', '.join(CASES)}")
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--json-out", type=Path, default=None)
    args = parser.parse_args(argv)
    if not (args.data / "rgb.txt").is_file():
        print(f"skipped: no Bonn crowd recording at {args.data}")
        return 0
    root = args.out_root or Path(tempfile.mkdtemp(prefix="bench_dynamic_"))
    rows = []
    print(f"{'case':<14} {'front-end ATE':>13} {'optimised ATE':>13} {'person':>6} {'retired':>7} {'s':>6}  landmarks")
    for name in [n.strip() for n in args.only.split(",") if n.strip()]:
        row = run_case(name, args.data, root / name, args.max_frames)
        rows.append(row)
        if row["rc"] != 0:
            print(f"{name:<14} FAILED (exit {row['rc']}): {' | '.join(row['error'])}")
            continue
        print(
            f"{name:<14} {row['ate_frontend_m']:>11.3f} m {row['ate_optimized_m']:>11.3f} m {row['persons']:>6} "
            f"{row['retired']:>7} {row['seconds']:>6.0f}  {row['landmarks']}",
            flush=True,
        )
    if args.json_out:
        args.json_out.write_text(json.dumps(rows, indent=1))
    if args.out_root is None:
        shutil.rmtree(root, ignore_errors=True)
    return 0 if all(r["rc"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
