"""Real time on the CPU at hand: the measured detector choice and what `semmap run --realtime` achieves.

    .venv/bin/python benchmarks/bench_realtime.py [--choice] [--runs 3] [--odometry orbslam3]
        [--data 7scenes,bonn,rpy] [--write docs/RESULTS.md] [--json-out F] [--keep DIR]
        [--realtime-args '--detectors 2 --set detector.precision=fp32 ...']

The front end is the one a user gets, ORB-SLAM3 (`--odometry orbslam3`); `gt` (simulated from ground truth) only as a
labelled reference (`--odometry orbslam3,gt`). Per run it also prints the share of the frames the front end posed
(`posed`), the ATE of the SLAM alone (its own poses) and of the final trajectory, and whether a person became a
landmark; `--write` puts the table between the `results:realtime` markers of a page. `--keep DIR` keeps every run's
output folder (its logs, stats.json, odometry_repair.json and trajectories) under DIR, to look into
a run that stood out.

1. `--choice`: measures every detector configuration on this machine (as `semmap models doctor --remeasure`) and
   prints the table: latency alone, CPU per frame, expected time per detection in a real-time run, F1 against
   fp32 640x480 and recall per class (cups and books are small).
2. Runs 7-Scenes redkitchen (1000 frames, 33.3 s of video) once in lockstep and `--runs` times in real time per
   odometry mode, each with nothing else set (`semmap run DATA --odometry MODE [--realtime] --out ...`), and prints
   per run: wall time (and its ratio to the video's length), frames detected, detections per 0.1 s of video,
   dropped frames, frames answered, landmarks (and their share of the lockstep run's), the planned and the
   achieved cadence (and the video time between detected frames as the tracker saw them, all replicas merged:
   `cadence_ms` p50 / p95 / max), the load average before the run (the machine is shared: quote medians), the
   CPU seconds the detectors got and the other services and `semmap run` itself took (on 2 cores the others'
   share is what the detectors lack);
   and which of the lockstep run's landmarks each real-time run missed (`missed`: class, first seen (s), lockstep
   observations; paired as `semmap diff` pairs two maps in one frame): the short-lived objects, or one lost another
   way; and which it mapped that lockstep did not (`gained`): a count is made of both. Last, per recording, the
   medians of the final ATE and of the share posed, and how many runs ended within 0.08 m.

Another machine, stood in: an AVX2-only CPU's kernels with benchmarks/avx2_stand_in.py
(`PYTHONPATH=DIR SEMMAP_MODEL_DIR=... python benchmarks/bench_realtime.py --choice ...`: every process of the runs
loads that onnxruntime), and slower cores with `--slower-cores 0.1` (a share of every core taken during each
real-time run).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from results_page import write_between_markers  # noqa: E402

from semmap.algorithms.evaluation import evaluate_run  # noqa: E402
from semmap.algorithms.map_merge import MatchParams, diff_maps  # noqa: E402
from semmap.core.messages import Landmark  # noqa: E402
from semmap.datasets import find_data_root  # noqa: E402
from semmap.runtime.maps.map_store import read_map_json  # noqa: E402
from semmap.runtime.models import detector_choice as dc  # noqa: E402

RECORDINGS = {"7scenes": "7scenes-redkitchen", "bonn": "bonn_crowd", "rpy": "tum_freiburg1_rpy"}


def run(data: Path, out: Path, odometry: str, realtime: bool, extra: list[str] | None = None,
        ) -> tuple[dict, list[Landmark]]:  # fmt: skip
    """One `semmap run` (real time: with `extra` arguments): its row of figures, and its map."""
    load = os.getloadavg()[0]
    cmd = [sys.executable, "-m", "semmap.cli", "run", str(data), "--odometry", odometry, "--out", str(out),
           "--overwrite", "--quiet"] + (["--realtime", *(extra or [])] if realtime else [])  # fmt: skip
    # the project first, then what the caller set (e.g. benchmarks/avx2_stand_in.py's onnxruntime, which every
    # process of the run must load)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)}
    t0, cpu0 = time.monotonic(), _children_cpu_s()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall, cpu = time.monotonic() - t0, _children_cpu_s() - cpu0  # the run and every service it waited for
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-2000:]}")
    stats = json.loads((out / "stats.json").read_text())
    mapped = read_map_json(out / "map.json")
    frames = stats["frames"]
    video_s = frames["published"] / 30.0
    odometry_services = [s for s in stats["services"].values() if s.get("service") == "odometry"]
    answered = sum(s["counters"].get("poses_published", 0) for s in odometry_services)
    # frames the front end posed itself (not bridged by semmap's stand-in where the SLAM had lost track)
    missing = sum(s["counters"].get("repair_slam_missing", 0) for s in odometry_services)
    budget = stats.get("detector_budget") or {}
    # what the detectors got of the CPU, and what everything else took from them (start-up included)
    detector_cpu = sum(s.get("cpu_s", 0.0) for s in stats["services"].values() if s.get("service") == "detector")
    services_cpu = sum(s.get("cpu_s", 0.0) for s in stats["services"].values())
    ate = evaluate_run(out) if (out / "groundtruth.tum").is_file() else {}
    return {
        "data": data.name, "odometry": odometry, "mode": "realtime" if realtime else "lockstep",
        "wall_s": round(wall, 1), "x_video": round(wall / video_s, 2), "load_before": round(load, 2),
        "detected": frames["detected"], "per_0.1s": round(frames["detected"] / video_s / 10, 2),
        "dropped": frames["dropped"], "processed": frames["processed"], "published": frames["published"],
        "landmarks": len(mapped), "people": sum(lm.class_name == "person" for lm in mapped),
        "planned": budget.get("planned", {}).get("every_n_frames"),
        "detect_ms_p50": (budget.get("achieved") or {}).get("detect_ms_p50"), "poses": answered,
        "posed": round((answered - missing) / max(1, frames["published"]), 3),
        "ate_slam": ate.get("ate_slam_m"), "ate_final": ate.get("ate_optimized_m"),
        "cadence_ms": {k: round(v) for k, v in (stats.get("detection_interval_ms") or {}).items()},
        "detector": budget.get("detector"), "detector_cpu_s": round(detector_cpu, 1),
        "others_cpu_s": round(services_cpu - detector_cpu, 1), "run_cpu_s": round(cpu - services_cpu, 1),
    }, mapped


class SlowerCores:
    """One process per core busy `share` of every 33 ms while the block runs: every other process gets that much
    less of each core, as on a CPU whose cores are slower by about that share (measured: an AVX2 EPYC's core
    takes ~11 % longer a detection than a VNNI EPYC's). A stand-in, not a measurement of such a CPU."""

    LONGEST_S = 600.0  # a burner ends by itself after this, should the block never exit

    def __init__(self, share: float) -> None:
        import multiprocessing

        self.share = share
        self._ctx = multiprocessing.get_context("spawn")
        self._start = self._ctx.Event()  # (held here: the children open it after they start)
        self._start.set()
        self._procs: list[Any] = []

    def __enter__(self) -> SlowerCores:
        if self.share > 0:
            self._procs = [self._ctx.Process(target=dc.burn, args=(self.share, self._start, self.LONGEST_S),
                                             daemon=True)
                           for _ in range(os.cpu_count() or 1)]  # fmt: skip
            for proc in self._procs:
                proc.start()
        return self

    def __exit__(self, *exc: object) -> None:
        for proc in self._procs:  # (a busy loop holds nothing: ended at once)
            proc.kill()
            proc.join(timeout=5.0)


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def missed_and_gained(reference: list[Landmark], mapped: list[Landmark]) -> tuple[list[str], list[str]]:
    """The reference map's landmarks that `mapped` (same frame) lacks, and those it has that the reference lacks, as
    `semmap diff` pairs them (no pairing of far-apart ones as moved): "class @first-seen s (observations)". A count
    of landmarks is the reference's less the missed plus the gained: which objects make it up says more."""
    diff = diff_maps(reference, mapped, MatchParams(move_radius_m=0.0))
    return ([f"{lm.class_name} @{lm.first_seen:.1f}s ({lm.observations})" for lm in diff.missing],
            [f"{lm.class_name} @{lm.first_seen:.1f}s ({lm.observations})" for lm in diff.added])  # fmt: skip


def _range(values: list[float | None], fmt: str = "{:.3f}") -> str:
    known = sorted(v for v in values if v is not None)
    if not known:
        return "-"
    return fmt.format(known[0]) if known[0] == known[-1] else f"{fmt.format(known[0])}-{fmt.format(known[-1])}"


def table(results: list[dict], cpu: str, runs: int) -> str:
    """The page's table: one row per recording and front end, the range over the real-time runs."""
    lines = [f"{cpu}; {runs} real-time runs each (their range), lockstep once for the landmark count.", "",
             "| recording | odometry | wall / video | front end posed | SLAM alone | final | detections per 0.1 s | "
             "landmarks (lockstep) | person landmarks |", "|---|---|---|---|---|---|---|---|---|"]
    keys = sorted({(r["data"], r["odometry"]) for r in results}, key=lambda k: (k[0], k[1] == "gt", k[1]))
    for data, odometry in keys:
        rt = [r for r in results if (r["data"], r["odometry"]) == (data, odometry) and r["mode"] == "realtime"]
        lock = [r for r in results if (r["data"], r["odometry"]) == (data, odometry) and r["mode"] == "lockstep"]
        if not rt:
            continue
        label = f"`{odometry}`" + (" (SIMULATED from ground truth: a reference)" if odometry.startswith("gt") else "")
        lines.append(
            f"| {data} | {label} | {_range([r['x_video'] for r in rt], '{:.2f}')} | "
            f"{_range([r['posed'] for r in rt], '{:.0%}')} | {_range([r['ate_slam'] for r in rt])} m | "
            f"{_range([r['ate_final'] for r in rt])} m | {_range([r['per_0.1s'] for r in rt], '{:.2f}')} | "
            f"{' / '.join(str(r['landmarks']) for r in rt)} ({lock[0]['landmarks'] if lock else '-'}) | "
            f"{max(r['people'] for r in rt)} |")
    return "\n".join(lines)


def medians(results: list[dict]) -> str:
    """Per recording and front end over the real-time runs: the medians of the final ATE and of the share posed,
    and how many runs ended within 0.08 m (where the runs vary as much as they do with walkers in view, the range
    alone says little)."""
    import statistics

    lines = []
    for data, odometry in dict.fromkeys((r["data"], r["odometry"]) for r in results if r["mode"] == "realtime"):
        runs = [r for r in results if (r["data"], r["odometry"], r["mode"]) == (data, odometry, "realtime")]
        finals = [r["ate_final"] for r in runs if r.get("ate_final") is not None]
        posed = [r["posed"] for r in runs if r.get("posed") is not None]
        lines.append(f"{data} {odometry}: {len(runs)} real-time runs, final ATE median "
                     + (f"{statistics.median(finals):.3f} m, {sum(f <= 0.08 for f in finals)} within 0.08 m"
                        if finals else "-")
                     + (f", front end posed median {statistics.median(posed):.0%}" if posed else ""))
    return "\n".join(lines)


def cpu_name() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.SubprocessError):
        return "unknown CPU"
    name = next((line.split(":", 1)[1].strip() for line in out.splitlines() if line.startswith("Model name")), "?")
    flags = next((line.split(":", 1)[1].split() for line in out.splitlines() if line.startswith("Flags")), [])
    extras = [f for f in ("avx512f", "avx512_vnni", "amx_int8") if f in flags]
    return f"{name}, {os.cpu_count()} cores ({', '.join(extras) or 'AVX2, no AVX-512'})"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--choice", action="store_true", help="measure the detector configurations first")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--odometry", default="orbslam3",
                    help="front ends, comma-separated; `gt` (simulated) only as a reference")
    ap.add_argument("--data", default="7scenes", help="recordings: " + ", ".join(RECORDINGS))
    ap.add_argument("--no-lockstep", action="store_true", help="skip the lockstep reference runs")
    ap.add_argument("--write", type=Path, default=None, help="a page with results:realtime markers to rewrite")
    ap.add_argument("--json-out", type=Path, default=None)
    ap.add_argument("--keep", type=Path, default=None, metavar="DIR",
                    help="keep every run's output folder under DIR (default: a temporary folder, removed)")
    ap.add_argument("--slower-cores", type=float, default=0.0, metavar="SHARE",
                    help="during each real-time run, take SHARE of every core (0.1: cores ~10 %% slower), a stand-in "
                         "for a slower CPU; its CPU is not counted in the run's figures")  # fmt: skip
    ap.add_argument("--realtime-args", default="",
                    help="more arguments for the real-time runs, e.g. another machine's choice: '--detectors 2 "
                         "--set detector.threads=1 --set detector.precision=fp32 --set detector.input_size=512x384' "
                         "(an AVX2-only EPYC's, replayed on a VNNI machine)")  # fmt: skip
    args = ap.parse_args()
    root = find_data_root()
    if root is None or not (root / "7scenes-redkitchen").is_dir():
        print("skipped: no ../shared/data", file=sys.stderr)
        return 0
    if args.choice:
        doc = dc.measure_and_save(root / "7scenes-redkitchen", progress=lambda line: print(line, file=sys.stderr))
    else:
        doc = dc.load_choice()
    if doc is not None:
        print(dc.format_table(doc))
    results = []
    with tempfile.TemporaryDirectory(prefix="semmap-rt-") as scratch:
        tmp = scratch if args.keep is None else str(args.keep)
        for name in args.data.split(","):
            data = root / RECORDINGS[name]
            for odometry in args.odometry.split(","):
                lock, lock_map = (None, []) if args.no_lockstep else run(data, Path(tmp) / f"lock-{name}-{odometry}",
                                                                         odometry, False)
                if lock:
                    results.append(lock)
                    print(json.dumps(lock), flush=True)
                for i in range(args.runs):
                    with SlowerCores(args.slower_cores):
                        r, mapped = run(data, Path(tmp) / f"rt-{name}-{odometry}-{i}", odometry, True,
                                        shlex.split(args.realtime_args))  # fmt: skip
                    if args.slower_cores:
                        r["slower_cores"] = args.slower_cores
                    if lock:
                        r["landmarks_vs_lockstep"] = round(r["landmarks"] / max(1, lock["landmarks"]), 2)
                        r["missed"], r["gained"] = missed_and_gained(lock_map, mapped)
                    results.append(r)
                    print(json.dumps(r), flush=True)
    text = table(results, cpu_name(), args.runs)
    print(text)
    print(medians(results))
    if args.write is not None:
        write_between_markers(args.write, "realtime", text)
    if args.json_out:
        args.json_out.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
