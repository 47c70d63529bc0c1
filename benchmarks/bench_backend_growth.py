"""Backend cost as the graph grows, replayed offline from a run's journal (no bus, no detector: seconds per
thousand frames instead of minutes, and a profile of where the time goes).

    .venv/bin/python benchmarks/bench_backend_growth.py OUT_DIR [--block 1000] [--profile] [--heap]
        [--set section.key=value]

OUT_DIR is a `semmap run` output folder (its `backend.sqlite` journal holds every handled frame's odometry,
observations and keyframe cloud). Each frame goes through the backend's own steps (PoseGraph update, loop-closure
search and ICP on keyframes, the corrected-poses delta and its encoding) and the script prints p50 / p95 per
step for each block of frames, the bytes per `poses/corrected` message, the kept keyframe-cloud memory and the
process's RSS; `--heap` adds the Python heap (tracemalloc: what the backend's own tables hold, without the
allocator's slack that RSS carries; slower).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from semmap.algorithms.backend.loop_closure import decode_keyframe  # noqa: E402
from semmap.core.config import load_config  # noqa: E402
from semmap.core.journal import FrameJournal  # noqa: E402
from semmap.core.messages import Observations, OdometryPose  # noqa: E402
from semmap.runtime.pipeline.stages import BackendStage  # noqa: E402
from semmap.runtime.transport.service import rss_mb  # noqa: E402

STEPS = ("update", "loop_closure", "publish")


HEADER = (
    f"{'frames':>7} {'nodes':>6} "
    + " ".join(f"{s + ' p50/p95 ms':>24}" for s in STEPS)
    + f" {'B/msg':>8} {'clouds MB':>9} {'RSS MB':>7} {'heap MB':>7}"
)


def print_row(r: dict) -> None:
    print(
        f"{r['frames']:>7} {r['nodes']:>6} "
        + " ".join(f"{r[s][0]:>11.2f} / {r[s][1]:>10.2f}" for s in STEPS)
        + f" {r['bytes_per_msg']:>8.0f} {r['kept_clouds_mb']:>9.1f} {r['rss_mb']:>7.1f}"
        + (f" {r['heap_mb']:>7.1f}" if r["heap_mb"] is not None else f" {'-':>7}"),
        flush=True,
    )


def replay(out_dir: Path, overrides: list[str], block: int) -> list[dict]:
    config = load_config(None, overrides)
    # the backend service's stage (semmap/runtime/pipeline/stages.py), built as the service builds it
    stage = BackendStage(config.backend, config.loop_closure, config.corrections)
    journal = FrameJournal(out_dir / "backend.sqlite")
    rows: list[dict] = []
    samples: dict[str, list[float]] = {s: [] for s in STEPS}
    sizes: list[int] = []
    for n, (frame_id, odometry, observations, keyframe) in enumerate(journal.frames(), start=1):
        cloud = decode_keyframe(keyframe)[0] if keyframe is not None else None
        # the search and ICP again, as the live backend does
        step = stage.step(OdometryPose.decode(odometry), Observations.decode(observations), cloud)
        t2 = time.perf_counter()
        payload = step.message("robot1", n, frame_id).encode()
        samples["update"].append(step.update_ms)
        if step.loop_closure_ms is not None:
            samples["loop_closure"].append(step.loop_closure_ms)
        samples["publish"].append(step.timing_ms["publish"] + (time.perf_counter() - t2) * 1e3)
        sizes.append(len(payload))
        if n % block == 0:
            row = {
                "frames": n,
                "nodes": stage.graph.num_nodes,
                "kept_clouds_mb": stage.closer.nbytes / 1e6,
                "bytes_per_msg": float(np.mean(sizes)),
                "rss_mb": rss_mb(),  # the process's resident memory: graph, kept clouds, publisher state
                "heap_mb": tracemalloc.get_traced_memory()[0] / 1e6 if tracemalloc.is_tracing() else None,
            }
            for step, values in samples.items():
                a = np.asarray(values) if values else np.zeros(1)
                row[step] = (float(np.percentile(a, 50)), float(np.percentile(a, 95)))
            rows.append(row)
            print_row(row)
            samples = {s: [] for s in STEPS}
            sizes = []
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--block", type=int, default=1000)
    parser.add_argument("--profile", action="store_true", help="print the 25 most expensive calls")
    parser.add_argument("--heap", action="store_true", help="also trace the Python heap (tracemalloc)")
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    args = parser.parse_args()
    if not (args.out_dir / "backend.sqlite").exists():
        parser.error(f"{args.out_dir} has no backend.sqlite journal")
    profiler = cProfile.Profile() if args.profile else None
    if profiler is not None:
        profiler.enable()
    if args.heap:
        tracemalloc.start()
    print(HEADER, flush=True)
    replay(args.out_dir, args.overrides, args.block)
    if profiler is not None:
        profiler.disable()
        pstats.Stats(profiler).sort_stats("cumulative").print_stats(25)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
