"""End-to-end performance of the real pipeline on 7-Scenes, per stage, like the paper's runtime table.

Runs `semmap run` twice (separate processes over Zenoh, real ONNX detector):
1. lockstep: sustained fps when every frame goes through every stage, one at a time;
2. real time at the dataset's 30 fps, detecting every `--detect-every`-th frame (the keyframes): frames
   dropped, end-to-end latency from a frame's publication to its map update.
Prints a table (p50 / p95 ms per stage, CPU and peak RSS per service) and writes JSON with `--json-out`.

    .venv/bin/python benchmarks/bench_perf.py [--frames 300] [--detect-every 3] [--json-out perf.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

PROJECT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(PROJECT))

from semmap.datasets import find_data_root  # noqa: E402

# (service, timing name, row label, paper's figure in ms on a Ryzen 3950X + RTX 2080 Ti, target here)
STAGES = [
    ("detector", "detect_ms", "detection (YOLOv5s, CPU)", "22.62 (GPU)", "<= 40 p50"),
    ("tracker", "proposal_ms", "candidate proposal (IOU tracker)", "0.069", "<= 0.1 p50"),
    ("associator", "proposal_ms", "back-projection + validation", "-", "-"),
    ("associator", "association_ms", "candidate association, step 1", "7.8", "<= 2 p50"),
    ("associator", "pointcloud_ms", "association step 2 (point-cloud NN)", "+150", "<= 20 p50"),
    ("associator", "update_merge_ms", "landmark update & merge", "23.16", "<= 5 p50"),
    ("associator", "refine_ms", "refinement after pose-graph update", "-", "-"),
    ("associator", "process_ms", "associator, all steps per frame", "-", "<= 2 p50, <= 20 p99"),
    ("backend", "update_ms", "backend update (iSAM2)", "-", "<= 10 p50"),
    ("backend", "keyframe_cloud_ms", "keyframe depth cloud (every 10th frame)", "-", "-"),
    ("backend", "loop_closure_ms", "loop-closure search + ICP (per keyframe)", "-", "-"),
    ("viz", "log_frame_ms", "Rerun sink, per frame", "-", "-"),
    ("associator", "end_to_end_ms", "end to end: frame -> map update", "65 per cycle", "<= 100 p95"),
]


def run(data: Path, out: Path, mode: str, frames: int, detect_every: int, precision: str) -> dict:
    cmd = [sys.executable, "-m", "semmap.cli", "run", str(data), "--out", str(out), f"--{mode}", "--odometry", "gt",
           "--max-frames", str(frames), "--quiet", "--overwrite", "--set", f"detector.every_n_frames={detect_every}",
           "--set", f"detector.precision={precision}"]
    result = subprocess.run(cmd, cwd=PROJECT, capture_output=True, text=True, env={**os.environ, "CI": "true"})
    if result.returncode != 0:
        raise SystemExit(f"semmap run failed:\n{result.stderr[-3000:]}")
    return json.loads((out / "stats.json").read_text())


def timing(stats: dict, service: str, name: str) -> dict | None:
    for s in stats["services"].values():
        if s.get("service") == service and name in s.get("timings_ms", {}):
            return s["timings_ms"][name]
    return None


def fmt(t: dict | None) -> str:
    if t is None:
        return "-"
    digits = 3 if t["p50"] < 1 else 1
    return f"{t['p50']:.{digits}f} / {t['p95']:.{digits}f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=None, help="dataset (default: ../shared/data/7scenes-redkitchen)")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--detect-every", type=int, default=3, help="real time: detect every n-th frame")
    parser.add_argument("--precision", default="int8", choices=("fp32", "int8"), help="detector model")
    parser.add_argument("--json-out", default=None)
    args = parser.parse_args()
    root = find_data_root()
    data = Path(args.data) if args.data else (root / "7scenes-redkitchen" if root else None)
    if data is None or not data.exists():
        raise SystemExit("no dataset: pass --data or provide ../shared/data")
    with tempfile.TemporaryDirectory() as tmp:
        lock = run(data, Path(tmp) / "lockstep", "lockstep", args.frames, 1, args.precision)
        real = run(data, Path(tmp) / "realtime", "realtime", args.frames, args.detect_every, args.precision)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.1f}; {args.frames} frames of {data.name}, detector {args.precision}")
    print(f"lockstep (every frame detected): {lock['fps']:.1f} fps sustained")
    print(f"real time 30 fps, detecting every {args.detect_every}rd frame: {real['frames']['dropped']} of "
          f"{real['frames']['published']} frames dropped, {real['frames']['detected']} detected")
    print()
    print(f"{'stage (ms, p50 / p95)':<40} {'lockstep':>16} {'real time':>16} {'paper':>14} {'target':>22}")
    rows = []
    for service, name, label, paper, target in STAGES:
        a, b = timing(lock, service, name), timing(real, service, name)
        rows.append({"stage": label, "service": service, "timing": name, "lockstep": a, "realtime": b,
                     "paper_ms": paper, "target": target})
        print(f"{label:<40} {fmt(a):>16} {fmt(b):>16} {paper:>14} {target:>22}")
    print()
    print(f"{'service':<12} {'CPU s (lockstep)':>17} {'peak RSS MB':>12} {'CPU s (real time)':>18} {'peak RSS MB':>12}")
    usage = []
    for name in sorted(lock["services"]):
        a = lock["services"][name]
        b = real["services"].get(name, {})
        usage.append({"service": name, "lockstep": {"cpu_s": a.get("cpu_s"), "peak_rss_mb": a.get("peak_rss_mb")},
                      "realtime": {"cpu_s": b.get("cpu_s"), "peak_rss_mb": b.get("peak_rss_mb")}})
        print(f"{name:<12} {a.get('cpu_s', 0):>17.1f} {a.get('peak_rss_mb', 0):>12.0f} "
              f"{b.get('cpu_s', 0):>18.1f} {b.get('peak_rss_mb', 0):>12.0f}")
    if args.json_out:
        Path(args.json_out).write_text(json.dumps({
            "frames": args.frames, "detect_every": args.detect_every, "lockstep_fps": lock["fps"],
            "realtime": real["frames"], "stages": rows, "services": usage,
            "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count()}}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
