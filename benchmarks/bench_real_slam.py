"""Real SLAMs on real recordings: the SLAM alone vs after semmap, with landmark factors off and on (docs/RESULTS.md).

    python benchmarks/bench_real_slam.py [--runs 3] [--only bonn-orbslam3,...] [--json-out FILE]

Each row runs the in-process driver (semmap/runtime/pipeline/inprocess.py: the services' stages in one process, lockstep
order) twice: `backend.landmark_constraints` false (the repaired odometry + depth loop closures) and true (the
whole system). ORB-SLAM3 is not deterministic: its rows run `--runs` times and print the median. Columns:
- SLAM alone: the SLAM's own poses (ORB-SLAM3's as tracked, or the file's), before semmap touched them;
- repaired: the odometry semmap hands its backend, after the step check (odometry.repair);
- landmarks off / on: the optimised trajectory without and with the landmark factors;
- overruled: SLAM steps semmap replaced (by its registration, or as breaking the recent motion), of all steps.
Every figure is ATE RMSE (evo: nearest stamp within 10 ms, SE(3) alignment) against the dataset's ground truth.
Needs ../shared/data (or $SEMMAP_DATA) and, for ORB-SLAM3 rows, the pyorbslam3 wheel and its vocabulary there.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from semmap.datasets import find_data_root  # noqa: E402
from semmap.runtime.pipeline.inprocess import closed_loop  # noqa: E402


def rows(data: Path) -> list[dict]:
    vocab = data / "orbslam3" / "ORBvoc_redkitchen_k10L5.txt"
    bonn, kitchen = str(data / "bonn_crowd"), str(data / "7scenes-redkitchen")
    orb = [f"odometry.orbslam3_vocabulary={vocab}"]
    out = [
        {"name": "bonn-orbslam3", "data": bonn, "odometry": "orbslam3", "set": orb, "repeat": True,
         "what": "Bonn crowd, ORB-SLAM3 live (semmap's masks before tracking)"},
        {"name": "bonn-orbslam3-norepair", "data": bonn, "odometry": "orbslam3", "repeat": True,
         "set": [*orb, "odometry.repair=false"], "what": "Bonn crowd, ORB-SLAM3 live, masks only (no repair)"},
        {"name": "7scenes-orbslam3", "data": kitchen, "odometry": "orbslam3", "set": orb, "repeat": True,
         "frames": 500, "what": "7-Scenes redkitchen frames 0-499 (static), ORB-SLAM3 live"},
        {"name": "bonn-rgbd", "data": bonn, "odometry": "rgbd", "set": [], "repeat": False,
         "what": "Bonn crowd, built-in rgbd (people masked)"},
    ]
    for run in (1, 2, 3):
        traj = data / "orbslam3" / f"bonn_crowd_orbslam3_run{run}.tum"
        out.append({"name": f"bonn-file-run{run}", "data": bonn, "odometry": f"file:{traj}", "set": [],
                    "repeat": False, "what": f"Bonn crowd, shared ORB-SLAM3 run {run} (unmasked) as file:"})
    return out


def command(row: dict, landmarks: bool) -> str:
    sets = " ".join(f"--set {s}" for s in [*row["set"], f"backend.landmark_constraints={str(landmarks).lower()}"])
    frames = f" --frames {row['frames']}" if row.get("frames") else ""
    return f"python -m semmap.runtime.pipeline.inprocess {row['data']}{frames} --odometry {row['odometry']} {sets}"


def run_row(row: dict, runs: int, frames: int) -> dict:
    result: dict = {"name": row["name"], "what": row["what"], "runs": []}
    for _ in range(runs if row["repeat"] else 1):
        one = {}
        for landmarks in (False, True):
            t0 = time.perf_counter()
            res, _ = closed_loop(row["data"], row["odometry"], frames=row.get("frames", frames),
                                 overrides=[*row["set"], f"backend.landmark_constraints={str(landmarks).lower()}"])
            key = "on" if landmarks else "off"
            one[f"ate_{key}"] = res.ate_optimized
            one.setdefault("ate_slam", res.ate_slam)
            one.setdefault("ate_repaired", res.ate_odometry)
            one[f"observations_{key}"] = res.observation_factors
            one[f"landmarks_{key}"] = res.landmarks
            one[f"classes_{key}"] = res.classes
            c = res.frontend_counters
            one.setdefault("overruled", c.get("repair_overruled", 0) + c.get("repair_implausible", 0))
            one.setdefault("steps", c.get("repair_steps", 0))
            one[f"wall_{key}_s"] = round(time.perf_counter() - t0, 1)
        result["runs"].append(one)
        print(f"  {row['name']}: {one}", file=sys.stderr, flush=True)
    for key in ("ate_slam", "ate_repaired", "ate_off", "ate_on"):
        values = [r[key] for r in result["runs"] if r.get(key) is not None]
        result[key] = statistics.median(values) if values else None
    result["commands"] = [command(row, False), command(row, True)]
    return result


def fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3, help="runs of each nondeterministic (ORB-SLAM3) row; median")
    ap.add_argument("--only", default=None, help="comma-separated row names")
    ap.add_argument("--frames", type=int, default=0, help="frames per run (0 = all)")
    ap.add_argument("--json-out", type=Path, default=None)
    args = ap.parse_args(argv)
    data = find_data_root()
    if data is None:
        print("error: no ../shared/data (set SEMMAP_DATA)", file=sys.stderr)
        return 2
    chosen = rows(data)
    if args.only:
        names = set(args.only.split(","))
        chosen = [r for r in chosen if r["name"] in names]
    results = []
    print("| row | SLAM alone | repaired | landmarks off | landmarks on | overruled | observations | landmarks |")
    print("|---|---|---|---|---|---|---|---|")
    for row in chosen:
        r = run_row(row, args.runs, args.frames)
        results.append(r)
        last = r["runs"][-1]
        print(f"| {r['what']} | {fmt(r['ate_slam'])} | {fmt(r['ate_repaired'])} | {fmt(r['ate_off'])} | "
              f"{fmt(r['ate_on'])} | {last['overruled']}/{last['steps']} | {last['observations_on']} | "
              f"{last['landmarks_on']} {last['classes_on']} |", flush=True)
    if args.json_out is not None:
        args.json_out.write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
