"""The paper's KITTI row at street scale: KITTI 00's 3.7 km through the street world, every service a process.

    python benchmarks/bench_street.py [--trajectory ../shared/data/trajectories/KITTI_00_gt.txt]
        [--slam ../shared/data/trajectories/KITTI_00_ORB.txt] [--work out/street] [--frames N]
        [--only drift,slam] [--analyse-only] [--set section.key=value ...] [--json-out FILE]

Runs `semmap run synthetic:trajectory=TRAJ --lockstep` (oracle detector, 620x188 KITTI-like camera, depth to 40 m)
twice: `--odometry gt+drift` (the simulated drift of a car's odometry: `odometry.drift_profile` vehicle, per metre
driven) and `--odometry file:SLAM` (a real SLAM's estimate of the same drive, KITTI's 12-number format), and
prints for each, from the run's own files:

- frames and throughput: over the first 1000 frames and over all (from `semmap run`'s progress lines, timed from
  the first processed frame), and their ratio (>= 0.8 means the cost per frame stays flat);
- landmarks by class, same-class pairs closer than 1 m (duplicates), revisits (places recognised again after drift,
  whose landmarks were fused into the old ones) and the landmarks they fused;
- ATE (RMSE, SE(3)-aligned, `semmap eval`) of the odometry and of the optimised trajectory, and the change;
- per-stage timings (p50 / p95 ms) and the associator's memory per landmark (RSS growth / landmarks) and map.sqlite
  bytes per landmark.
`--analyse-only` reads the runs already in `--work`. A full drive takes ~11 min per run on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from semmap.datasets import find_data_root  # noqa: E402

DATA = (find_data_root() or ROOT.parent / "shared" / "data") / "trajectories"  # ../shared/data or $SEMMAP_DATA
PROGRESS = re.compile(r"(\d+)/(\d+) frames processed.*?([\d.]+) s\s*$")


def run(name: str, data: str, odometry: str, out: Path, frames: int, sets: list[str]) -> None:
    cmd = [sys.executable, "-m", "semmap.cli", "run", data, "--odometry", odometry, "--lockstep", "--out", str(out),
           "--overwrite"]
    if frames:
        cmd += ["--max-frames", str(frames)]
    for s in sets:
        cmd += ["--set", s]
    print("$ semmap " + " ".join(cmd[3:]), flush=True)
    t0 = time.perf_counter()
    with (out.parent / f"{name}.log").open("w") as log:
        code = subprocess.run(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, timeout=7200).returncode
    print(f"  exit {code} after {time.perf_counter() - t0:.0f} s", flush=True)
    if code != 0:
        raise SystemExit(f"{name}: semmap run failed ({code}); see {out.parent / f'{name}.log'}")


def throughput(log: Path) -> dict[str, float]:
    """Frames per second over the first 1000 frames and over all, from the progress lines (s since start)."""
    seen: dict[int, float] = {}
    for line in log.read_text(errors="replace").splitlines():
        m = PROGRESS.search(line)
        if m and int(m.group(1)) > 0:
            seen.setdefault(int(m.group(1)), float(m.group(3)))
    if len(seen) < 3:
        return {}
    done = sorted(seen)
    first, last = done[0], done[-1]
    at_1000 = min((k for k in done if k >= 1000), default=last)
    early = (at_1000 - first) / max(seen[at_1000] - seen[first], 1e-9)
    whole = (last - first) / max(seen[last] - seen[first], 1e-9)
    return {"fps_first_1000": early, "fps_all": whole, "ratio": whole / early, "frames": last}


def analyse(name: str, out: Path) -> dict:
    landmarks = json.loads((out / "map.json").read_text())["landmarks"]
    stats = json.loads((out / "stats.json").read_text())
    ev = json.loads((out / "eval.json").read_text()) if (out / "eval.json").is_file() else {}
    centroids = np.array([lm["centroid"] for lm in landmarks], float).reshape(-1, 3)
    classes = [lm["class"] for lm in landmarks]
    close = [(i, j) for i, j in cKDTree(centroids).query_pairs(1.0) if classes[i] == classes[j]] if landmarks else []
    assoc = stats["services"]["associator"]
    timings = {f"{svc}.{k}": (round(v["p50"], 1), round(v["p95"], 1))
               for svc, s in stats["services"].items() for k, v in (s.get("timings_ms") or {}).items()
               if isinstance(v, dict) and "p50" in v}
    store = out / "map.sqlite"
    n = max(len(landmarks), 1)
    return {
        "name": name,
        "landmarks": len(landmarks),
        "classes": dict(Counter(classes).most_common()),
        "same_class_within_1m": len(close),
        "revisits": assoc["counters"].get("revisits", 0),
        "revisit_fused_landmarks": assoc["counters"].get("revisit_fused_landmarks", 0),
        "ate_odometry_m": ev.get("ate_odometry_m"),
        "ate_optimized_m": ev.get("ate_optimized_m"),
        "improvement_pct": ev.get("improvement_pct"),
        **throughput(out.parent / f"{name}.log"),
        "associator_kb_per_landmark": round(1024 * (assoc["rss_late_mb"] - assoc["rss_early_mb"]) / n, 1),
        "map_sqlite_kb_per_landmark": round(store.stat().st_size / 1024 / n, 1) if store.is_file() else None,
        "timings_ms_p50_p95": timings,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trajectory", type=Path, default=DATA / "KITTI_00_gt.txt")
    ap.add_argument("--slam", type=Path, default=DATA / "KITTI_00_ORB.txt")
    ap.add_argument("--work", type=Path, default=ROOT / "out" / "street")
    ap.add_argument("--frames", type=int, default=0, help="0 = the whole drive")
    ap.add_argument("--only", default="drift,slam")
    ap.add_argument("--analyse-only", action="store_true")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--json-out", type=Path, default=None)
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    data = f"synthetic:trajectory={args.trajectory.resolve()}"
    runs = {"drift": "gt+drift", "slam": f"file:{args.slam.resolve()}"}
    results = []
    for name in [s.strip() for s in args.only.split(",") if s.strip()]:
        out = args.work / name
        if not args.analyse_only:
            run(name, data, runs[name], out, args.frames, args.sets)
            subprocess.run([sys.executable, "-m", "semmap.cli", "eval", str(out)], cwd=ROOT, check=True,
                           stdout=subprocess.DEVNULL, timeout=600)
        result = analyse(name, out)
        results.append(result)
        print(json.dumps(result, indent=1), flush=True)
    if args.json_out is not None:
        args.json_out.write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
