"""Do no harm: the SLAM alone against the SLAM after semmap, on every real recording at hand.

    python benchmarks/bench_no_harm.py [--runs 3] [--only bonn,rpy,7scenes] [--fronts live,file,rgbd]
        [--write docs/RESULTS.md] [--json-out FILE]

Per recording (7-Scenes redkitchen, Bonn crowd, the TUM fr1_rpy window) and front end:
- `live`: ORB-SLAM3 through `--odometry orbslam3` (semmap's masks before it tracks, its steps checked);
- `file`: an external ORB-SLAM3 trajectory through `--odometry file:` (the shared runs where the data has them,
  else the trajectory the live run's ORB-SLAM3 wrote itself, unmasked by nothing semmap did to it after);
- `rgbd`: the built-in front end (there is no SLAM to harm: its own chain against the final trajectory).
Each row is the median of `--runs` runs (ORB-SLAM3 is not deterministic) of the in-process driver
(`python -m semmap.runtime.pipeline.inprocess`, the services' stages in lockstep order). *SLAM alone* is the ATE of the
SLAM's own poses (`trajectory_slam.tum` in a `semmap run`), *semmap* that of the final, optimised trajectory;
*no harm* holds where semmap's is at most max(1.1 x, SLAM alone + 3 mm). *SLAM refined at its end*: ORB-SLAM3's own
trajectory as it saves it after its last bundle adjustment (`trajectory_slam_refined.tum`), what it alone gives.
Figures are ATE RMSE against the recording's ground truth (evo association, SE(3) alignment). `--write` puts the
table between the `results:no-harm` markers of the page. Needs ../shared/data (or $SEMMAP_DATA) and the pyorbslam3
wheel with a vocabulary for the ORB-SLAM3 rows.
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from results_page import write_between_markers  # noqa: E402

from semmap.datasets import find_data_root  # noqa: E402
from semmap.datasets.trajectory_io import read_tum, write_tum  # noqa: E402
from semmap.runtime.models.model_store import default_vocabulary  # noqa: E402

RECORDINGS = {
    "7scenes": ("7scenes-redkitchen", "7-Scenes redkitchen (static, 1000 frames)", None),
    "bonn": ("bonn_crowd", "Bonn crowd (people walking, 477 frames)", "bonn_crowd_orbslam3_run{}.tum"),
    "rpy": ("tum_freiburg1_rpy", "TUM fr1_rpy 200-319 (a person sits still; fast turns)",
            "tum_freiburg1_rpy_orbslam3_run{}.tum"),
}
MARKER = "no-harm"


def no_harm(alone: float, final: float) -> bool:
    return final <= max(1.1 * alone, alone + 0.003)


def cpu_name() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=10).stdout
        name = re.search(r"Model name:\s*(.+)", out)
        flags = re.search(r"Flags:\s*(.+)", out)
        extras = [f for f in ("avx512f", "avx512_vnni", "amx_int8") if flags and f in flags.group(1).split()]
        return (name.group(1).strip() if name else platform.processor()) + (f" ({', '.join(extras)})" if extras
                                                                          else " (AVX2, no AVX-512)")
    except (OSError, subprocess.SubprocessError):
        return platform.processor() or "unknown CPU"


def one_run(data: Path, odometry: str, sets: list[str]) -> dict:
    """One in-process run in a process of its own (ORB-SLAM3 keeps state between instances in one process)."""
    with tempfile.TemporaryDirectory(prefix="semmap-noharm-") as tmp:
        out, summary = Path(tmp) / "run", Path(tmp) / "summary.json"
        cmd = [sys.executable, "-m", "semmap.runtime.pipeline.inprocess", str(data), "--odometry", odometry,
               "--out", str(out),
               "--json-out", str(summary), *[a for s in sets for a in ("--set", s)]]
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-2000:]}")
        result = json.loads(summary.read_text())
        result = result[0] if isinstance(result, list) else result
        slam_file = out / "trajectory_slam.tum"
        slam = read_tum(slam_file) if slam_file.is_file() else []
    c = result.get("frontend", {})
    alone = result.get("ate_slam_m")
    return {"alone": alone if alone is not None else result["ate_odometry_m"], "final": result["ate_optimized_m"],
            "refined": result.get("ate_slam_refined_m"),
            "overruled": c.get("repair_overruled", 0) + c.get("repair_implausible", 0),
            "steps": c.get("repair_steps", 0), "landmarks": result.get("landmarks", 0), "slam": slam}


def command(data: str, odometry: str, sets: list[str]) -> str:
    extra = "".join(f" --set {s}" for s in sets)
    return f"python -m semmap.runtime.pipeline.inprocess ../shared/data/{data} --odometry {odometry}{extra}"


def rows(root: Path, runs: int, only: list[str], fronts: list[str]) -> list[dict]:
    vocabulary = default_vocabulary()
    if vocabulary is None and (root / "orbslam3" / "ORBvoc_redkitchen_k10L5.txt").is_file():
        vocabulary = root / "orbslam3" / "ORBvoc_redkitchen_k10L5.txt"
    orb = [f"odometry.orbslam3_vocabulary={vocabulary}"] if vocabulary is not None else []
    out = []
    for key in only:
        folder, what, shared = RECORDINGS[key]
        data = root / folder
        live_slam: list[list] = []
        if "live" in fronts and orb:
            results = []
            for _ in range(runs):
                results.append(_timed(data, "orbslam3", orb))
                live_slam.append(results[-1].pop("slam"))
            out.append(_row(what, "ORB-SLAM3 live (`--odometry orbslam3`)", results,
                            command(folder, "orbslam3", ["odometry.orbslam3_vocabulary=VOCABULARY"])))
        if "file" in fronts:
            results, how = [], ""
            if shared is not None:
                for run in range(1, runs + 1):
                    trajectory = root / "orbslam3" / shared.format((run - 1) % 3 + 1)
                    results.append(_timed(data, f"file:{trajectory}", []))
                    results[-1].pop("slam")
                how = "the shared ORB-SLAM3 runs 1-3 (unmasked) as `--odometry file:`"
                cmd = command(folder, f"file:../shared/data/orbslam3/{shared.format(1)}", [])
            elif live_slam:
                with tempfile.TemporaryDirectory() as tmp:
                    for i, slam in enumerate(live_slam):
                        path = Path(tmp) / f"orbslam3_{i}.tum"
                        write_tum(path, slam)
                        results.append(_timed(data, f"file:{path}", []))
                        results[-1].pop("slam")
                how = "the live runs' own ORB-SLAM3 trajectories as `--odometry file:`"
                cmd = command(folder, "file:trajectory_slam.tum", [])
            if results:
                out.append(_row(what, how, results, cmd))
        if "rgbd" in fronts:
            result = _timed(data, "rgbd", [])
            result.pop("slam")
            out.append(_row(what, "built-in `rgbd` (its own chain -> final)", [result], command(folder, "rgbd", [])))
    return out


def _timed(data: Path, odometry: str, sets: list[str]) -> dict:
    t0 = time.perf_counter()
    result = one_run(data, odometry, sets)
    result["wall_s"] = round(time.perf_counter() - t0, 1)
    print(f"  {data.name} {odometry.split('/')[-1]}: alone {result['alone']:.4f} -> final {result['final']:.4f} "
          f"({result['wall_s']} s)", file=sys.stderr, flush=True)
    return result


def _row(what: str, front: str, results: list[dict], cmd: str) -> dict:
    alone = statistics.median(r["alone"] for r in results)
    final = statistics.median(r["final"] for r in results)
    runs = " / ".join(f"{r['alone']:.3f} -> {r['final']:.3f}" for r in results)
    refined = [r["refined"] for r in results if r.get("refined") is not None]
    steps = statistics.median(r["steps"] for r in results)
    overruled = statistics.median(r["overruled"] for r in results)
    return {"recording": what, "front": front, "alone": alone, "final": final, "runs": runs,
            "refined": statistics.median(refined) if refined else None,
            "harmless": all(no_harm(r["alone"], r["final"]) for r in results),
            "overruled": f"{overruled:.0f} of {steps:.0f}" if steps else "-", "command": cmd}


def table(found: list[dict], cpu: str, runs: int) -> str:
    lines = [f"In process, {cpu}; median of {runs} runs (each run's SLAM alone -> semmap in brackets).", "",
             "| recording | front end | SLAM alone | semmap | change | no harm | SLAM refined at its end | "
             "steps overruled | runs | command |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in found:
        change = 100.0 * (r["final"] - r["alone"]) / r["alone"] if r["alone"] else 0.0
        refined = "-" if r.get("refined") is None else f"{r['refined']:.3f} m"
        lines.append(f"| {r['recording']} | {r['front']} | {r['alone']:.3f} m | **{r['final']:.3f} m** | "
                     f"{change:+.0f} % | {'yes' if r['harmless'] else 'NO'} | {refined} | {r['overruled']} | "
                     f"{r['runs']} | `{r['command']}` |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--only", default=",".join(RECORDINGS), help="recordings: " + ", ".join(RECORDINGS))
    ap.add_argument("--fronts", default="live,file,rgbd")
    ap.add_argument("--write", type=Path, default=None, help="a page with results:no-harm markers to rewrite")
    ap.add_argument("--json-out", type=Path, default=None)
    args = ap.parse_args()
    root = find_data_root()
    if root is None:
        print("no ../shared/data (or $SEMMAP_DATA): nothing to measure", file=sys.stderr)
        return 2
    only = [k for k in args.only.split(",") if k]
    unknown = [k for k in only if k not in RECORDINGS]
    if unknown:
        ap.error(f"unknown recordings {unknown}: choose from {', '.join(RECORDINGS)}")
    found = rows(root, args.runs, only, [f for f in args.fronts.split(",") if f])
    text = table(found, cpu_name(), args.runs)
    print(text)
    if args.write is not None:
        write_between_markers(args.write, MARKER, text)
    if args.json_out is not None:
        args.json_out.write_text(json.dumps(found, indent=1))
    return 0 if all(r["harmless"] for r in found) else 1


if __name__ == "__main__":
    raise SystemExit(main())
