"""Trajectory accuracy with and without semantic landmarks, in the form of the paper's Table 1.

    python benchmarks/bench_matrix.py [--quick] [--json-out FILE] [--out-root DIR] [--only NAMES]
        [--offline] [--ablation] [--keep] [--set section.key=value]...

Runs the real pipeline (`semmap run DATA --out DIR --odometry MODE --seed N --quiet --no-viz`, lockstep, every
service its own process over Zenoh) and `semmap eval` on each case:

  7scenes-gt            ground-truth odometry with its tight declared covariance (must stay below 1 cm)
  7scenes-drift-s{0,1,2} `gt+drift`, the default drift (3 mm, 0.3 deg noise and 0.05 deg/frame yaw bias)
  7scenes-weak          weak drift (0.005 deg/frame bias, 1 mm): landmarks must not make it worse
  7scenes-rgbd          Open3D RGB-D odometry
  synthetic-drift       the synthetic room with two walking people (oracle detector), `gt+drift`

and prints sequence, odometry, baseline ATE (the odometry's), ATE with landmark constraints only (loop
closures off: the "centroid floor"), ATE of the whole system (landmarks + depth loop closures), its
improvement, landmarks, observations sent to the backend, loop closures (and, on synthetic data, landmarks on
a person). `--ablation` adds the loop closures without landmark constraints (`backend.landmark_constraints:
false`), which shows what the landmarks do for the closures. `--quick` plays
300 frames of each (synthetic: 300 frames); `--offline` runs the in-process driver
(semmap/runtime/pipeline/inprocess.py)
instead of the pipeline (same stages, same numbers, seconds instead of minutes, cached detections). 7-Scenes cases
are skipped with a note when ../shared/data (or $SEMMAP_DATA) has no redkitchen.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

PROJECT = Path(__file__).resolve().parents[1]
WEAK = ["odometry.drift_yaw_bias_deg=0.005", "odometry.drift_translation_sigma_m=0.001"]
# each case runs once per variant: the whole system, and without one of its two kinds of constraints
VARIANTS = {"full": [], "semantic_only": ["loop_closure.enabled=false"],
            "loops_only": ["backend.landmark_constraints=false"]}


@dataclass
class Case:
    name: str
    data: str  # dataset path or synthetic spec
    odometry: str
    seed: int = 0
    overrides: list[str] = field(default_factory=list)
    label: str = ""  # the sequence column


def cases(seven: Path | None, quick: bool) -> list[Case]:
    synth_frames = 300 if quick else 600
    out = []
    if seven is not None:
        k = str(seven)
        out += [Case("7scenes-gt", k, "gt", label="redkitchen"),
                *[Case(f"7scenes-drift-s{s}", k, "gt+drift", s, label=f"redkitchen (seed {s})") for s in (0, 1, 2)],
                Case("7scenes-weak", k, "gt+drift", 0, list(WEAK), label="redkitchen (weak drift)"),
                Case("7scenes-rgbd", k, "rgbd", label="redkitchen")]
    out.append(Case("synthetic-drift", f"synthetic:frames={synth_frames}", "gt+drift", 0,
                    label=f"synthetic, {synth_frames} frames, 2 people"))
    return out


def seven_scenes() -> Path | None:
    from semmap.datasets import find_data_root

    root = find_data_root()
    path = None if root is None else root / "7scenes-redkitchen"
    return path if path is not None and path.is_dir() else None


def person_landmarks(landmarks: list, objects: list) -> tuple[int, int]:
    """(landmarks of a moving class, static objects mapped) on synthetic data (`objects`: its ground truth)."""
    from semmap.runtime.pipeline.inprocess import score_map

    moving = {o.class_name for o in objects if o.moving}
    score = score_map(landmarks, objects)
    return sum(1 for lm in landmarks if lm.class_name in moving), score.mapped


def run_pipeline(case: Case, out_dir: Path, max_frames: int | None, extra: list[str]) -> dict:
    from semmap.algorithms.evaluation import evaluate_run

    cmd = [sys.executable, "-m", "semmap.cli", "run", case.data, "--out", str(out_dir), "--odometry",
           case.odometry, "--seed", str(case.seed), "--quiet", "--no-viz", "--overwrite"]
    if max_frames:
        cmd += ["--max-frames", str(max_frames)]
    for item in [*case.overrides, *extra]:
        cmd += ["--set", item]
    t0 = time.monotonic()
    proc = subprocess.run(cmd, cwd=PROJECT, capture_output=True, text=True, env={**os.environ, "CI": "true"})
    wall = time.monotonic() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{case.name}: semmap run failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    ev = evaluate_run(out_dir)
    stats = json.loads((out_dir / "stats.json").read_text())["services"]
    counters = {name: s.get("counters", {}) for name, s in stats.items()}
    landmarks = json.loads((out_dir / "map.json").read_text())["landmarks"]
    backend = counters.get("backend", {})
    row = {"ate_odometry_m": ev["ate_odometry_m"], "ate_optimized_m": ev["ate_optimized_m"],
           "landmarks": len(landmarks), "observations": int(backend.get("observations", 0)),
           "merges": int(counters.get("associator", {}).get("merges", 0)), "poses": ev["poses"], "wall_s": wall,
           "loop_closures": int(backend.get("loop_closures", 0))}
    if case.data.startswith("synthetic"):
        from types import SimpleNamespace

        from semmap.datasets import open_dataset

        lms = [SimpleNamespace(id=d["id"], class_name=d["class"], centroid=d["centroid"]) for d in landmarks]
        row["person_landmarks"], row["objects_mapped"] = person_landmarks(lms, open_dataset(case.data).objects())
    return row


def run_offline(case: Case, max_frames: int | None, extra: list[str]) -> dict:
    from semmap.runtime.pipeline.inprocess import closed_loop

    t0 = time.monotonic()
    res, rec = closed_loop(case.data, case.odometry, case.seed, max_frames or 0, [*case.overrides, *extra])
    row = {"ate_odometry_m": res.ate_odometry, "ate_optimized_m": res.ate_optimized, "landmarks": res.landmarks,
           "observations": res.observations, "merges": res.merges, "poses": res.frames,
           "wall_s": time.monotonic() - t0, "loop_closures": res.loop_closures.get("accepted", 0)}
    if rec.objects:
        row["person_landmarks"], row["objects_mapped"] = person_landmarks(res.mapper.landmarks(), rec.objects)
    return row


def improvement(row: dict) -> float | None:
    """Percent lower than the odometry's ATE (None below a millimetre: `gt` odometry is exact)."""
    if row["ate_odometry_m"] < 1e-3:
        return None
    return 100.0 * (row["ate_odometry_m"] - row["ate_optimized_m"]) / row["ate_odometry_m"]


def _cm(value: float | None, width: int) -> str:
    return f"{'-':>{width}s}" if value is None else f"{value * 100:{width - 3}.2f} cm"


def print_table(rows: list[dict]) -> None:
    ablation = any("ate_loops_only_m" in r for r in rows)
    head = (f"{'case':18s} {'sequence':32s} {'odometry':9s} {'baseline ATE':>12s} {'landmarks only':>14s} "
            f"{'+ loop closures':>15s} {'improvement':>11s} " + (f"{'loops only':>11s} " if ablation else "")
            + f"{'landmarks':>9s} {'observations':>12s} {'closures':>8s} {'persons':>7s}")
    print(head)
    print("-" * len(head))
    for r in rows:
        imp = r.get("improvement_pct")
        imp_s = "n/a" if imp is None else f"{imp:+.1f} %"
        persons = str(r["person_landmarks"]) if "person_landmarks" in r else "-"
        print(f"{r['case']:18s} {r['sequence']:32s} {r['odometry']:9s} {_cm(r['ate_odometry_m'], 12)} "
              f"{_cm(r.get('ate_semantic_only_m'), 14)} {_cm(r['ate_optimized_m'], 15)} {imp_s:>11s} "
              + (f"{_cm(r.get('ate_loops_only_m'), 11)} " if ablation else "")
              + f"{r['landmarks']:9d} {r['observations']:12d} {r['loop_closures']:8d} {persons:>7s}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="300 frames per case")
    ap.add_argument("--offline", action="store_true",
                    help="the in-process driver (semmap/runtime/pipeline/inprocess.py) instead of the pipeline")
    ap.add_argument("--only", default=None, help="comma-separated case names (or prefixes)")
    ap.add_argument("--out-root", type=Path, default=Path("/tmp/semmap-bench-matrix"),
                    help="run folders (one per case)")
    ap.add_argument("--keep", action="store_true", help="keep the run folders")
    ap.add_argument("--ablation", action="store_true", help="also run loop closures without landmark constraints")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="extra settings for every case")
    ap.add_argument("--json-out", type=Path, default=None)
    args = ap.parse_args(argv)

    seven = seven_scenes()
    if seven is None:
        print("7-Scenes redkitchen not found (../shared/data or $SEMMAP_DATA): its cases are skipped")
    chosen = cases(seven, args.quick)
    if args.only:
        wanted = [w.strip() for w in args.only.split(",") if w.strip()]
        chosen = [c for c in chosen if any(c.name.startswith(w) for w in wanted)]
    max_frames = 300 if args.quick else None
    variants = ["full", "semantic_only"] + (["loops_only"] if args.ablation else [])
    rows = []
    for case in chosen:
        results = {}
        for variant in variants:
            out_dir = args.out_root / case.name / variant
            if out_dir.exists():
                shutil.rmtree(out_dir)
            print(f"running {case.name} ({variant}) ...", file=sys.stderr, flush=True)
            extra = [*VARIANTS[variant], *args.overrides]
            if args.offline:
                results[variant] = run_offline(case, max_frames, extra)
            else:
                out_dir.mkdir(parents=True, exist_ok=True)
                results[variant] = run_pipeline(case, out_dir, max_frames, extra)
                if not args.keep:
                    shutil.rmtree(out_dir, ignore_errors=True)
        row = {"case": case.name, "sequence": case.label, "data": case.data, "odometry": case.odometry,
               "seed": case.seed, "overrides": case.overrides + args.overrides, **results["full"]}
        for variant in variants[1:]:
            row[f"ate_{variant}_m"] = results[variant]["ate_optimized_m"]
        row["improvement_pct"] = improvement(row)
        rows.append(row)
        imp = row["improvement_pct"]
        print(f"  {case.name}: {row['ate_odometry_m'] * 100:.2f} -> {row['ate_semantic_only_m'] * 100:.2f} "
              f"(landmarks only) -> {row['ate_optimized_m'] * 100:.2f} cm"
              f"{'' if imp is None else f' ({imp:+.1f} %)'}, {sum(r['wall_s'] for r in results.values()):.0f} s",
              file=sys.stderr, flush=True)
    print()
    engine = "in-process driver (semmap/runtime/pipeline/inprocess.py)" if args.offline else "pipeline (semmap run)"
    print(f"engine: {engine}"
          f", {'300 frames' if args.quick else 'all frames'}")
    print_table(rows)
    if args.json_out is not None:
        args.json_out.parent.mkdir(parents=True, exist_ok=True)
        args.json_out.write_text(json.dumps({"engine": "offline" if args.offline else "pipeline",
                                             "quick": args.quick, "rows": rows}, indent=1) + "\n")
        print(f"\nwrote {args.json_out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
