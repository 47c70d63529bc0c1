"""What a real-time run maps on a machine you do not have: its detection schedule simulated, its map made in process.

    .venv/bin/python benchmarks/bench_schedule.py [DATA] --plan 512x384:2:2:120 [--plan 640x480:1:2:67:int8 ...]
        [--spread 0.25] [--frame-ms 33.3] [--seeds 8] [--reference 640x480] [--json-out F] [--cache-dir D]

A plan is LETTERBOX:EVERY_N:REPLICAS:DETECT_MS[:PRECISION]: the detector's letterbox, the planned cadence (every
n-th frame), the replicas taking turns, one detection's time *in the run* per replica (the `detector ... ms p50 in
the run` of a real-time run's summary on that machine, or its doctor's time beside the other services), and the
model's precision (fp32 by default, int8 or int8w7; int8's detections differ by CPU: they are computed on this
one). For each seed the replicas' turns are played against a clock (`semmap.algorithms.detector.turns.simulate`:
the detector service's own turn logic; detection times drawn log-normally around DETECT_MS with sigma `--spread`,
frames arriving every `--frame-ms`), and the frames it detects are mapped in process
(`semmap.runtime.pipeline.inprocess`,
`--odometry gt`, the detections of every frame at that letterbox computed once and cached). Each map is compared
with the lockstep map at `--reference` (every frame detected, as `semmap run --lockstep` maps), as `semmap diff`
pairs landmarks.

Why: real time decides which frames are detected, and which frames are detected decides what is mapped (evenly
spaced detections give more distinct views than the same number in pairs). Recording a live run's detections and
replaying them in process gives exactly the live map, so the map of a simulated schedule is what a run
with that schedule maps; what the simulation leaves out is how the detection times vary on the real machine.

Prints per plan: detections per second of video (per seed), landmarks per seed, their share of the reference's,
the runs at >= 90 % of it, and the reference's landmarks most often missed.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_realtime import missed_and_gained  # noqa: E402  (the same pairing and wording as the live runs')

from semmap.algorithms.detector.turns import simulate  # noqa: E402
from semmap.core.config import load_config  # noqa: E402
from semmap.core.messages import Detections, Landmark  # noqa: E402
from semmap.datasets import find_data_root  # noqa: E402
from semmap.runtime.models.model_store import QUANTIZED_FILES  # noqa: E402
from semmap.runtime.pipeline import inprocess  # noqa: E402


@dataclasses.dataclass(frozen=True)
class Plan:
    letterbox: str
    every_n: int
    replicas: int
    detect_ms: float
    precision: str = "fp32"

    @classmethod
    def parse(cls, text: str) -> Plan:
        try:
            size, every_n, replicas, detect_ms, *rest = text.split(":")
            if len(rest) > 1 or (rest and rest[0] not in ("fp32", *QUANTIZED_FILES)):
                raise ValueError
            plan = cls(size, int(every_n), int(replicas), float(detect_ms), *rest)
        except ValueError:
            raise argparse.ArgumentTypeError(f"plan {text!r}: want LETTERBOX:EVERY_N:REPLICAS:DETECT_MS[:PRECISION] "
                                             f"(fp32, int8, int8w7), e.g. 512x384:2:2:120") from None
        if plan.every_n < 1 or plan.replicas < 1 or plan.detect_ms <= 0:
            raise argparse.ArgumentTypeError(f"plan {text!r}: every_n and replicas >= 1, detect_ms > 0")
        return plan

    def __str__(self) -> str:
        return (f"{self.precision} {self.letterbox} every {self.every_n}, {self.replicas} replica(s), "
                f"{self.detect_ms:g} ms")


def recording(data: str, letterbox: str, precision: str = "fp32",
              cache_dir: Path = inprocess.CACHE_DIR) -> inprocess.Recording:  # fmt: skip
    """Every frame's detections at `letterbox` (cached by the in-process driver)."""
    config = load_config(None, [f"detector.input_size={letterbox}", "detector.every_n_frames=1",
                                f"detector.precision={precision}"])
    return inprocess.detect_recording(data, 0, config, cache_dir, verbose=False)


def masked(rec: inprocess.Recording, detected: set[int]) -> inprocess.Recording:
    """The recording with every frame not in `detected` answered as the service answers a skipped one."""
    dets = [d if d.frame_id in detected else
            Detections(d.robot, d.frame_id, d.stamp, d.intrinsics, d.depth_scale, [], "stride")
            for d in rec.detections]  # fmt: skip
    return dataclasses.replace(rec, detections=dets)


def map_of(rec: inprocess.Recording, letterbox: str) -> list[Landmark]:
    config = load_config(None, [f"detector.input_size={letterbox}", "odometry.mode=gt"])
    return inprocess.run_loop(rec, config, "gt").mapper.landmarks()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", nargs="?", default=None,
                    help="a dataset folder, or synthetic[:frames=N] (default: ../shared/data/7scenes-redkitchen)")
    ap.add_argument("--plan", type=Plan.parse, action="append", required=True)
    ap.add_argument("--spread", type=float, default=0.25, help="sigma of the log-normal detection times")
    ap.add_argument("--frame-ms", type=float, default=1000 / 30, help="time between frames arriving")
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--reference", default="640x480", help="letterbox of the lockstep reference map")
    ap.add_argument("--json-out", type=Path, default=None)
    ap.add_argument("--cache-dir", type=Path, default=inprocess.CACHE_DIR, help="where detections are cached")
    args = ap.parse_args(argv)
    data = args.data
    if data is None:
        root = find_data_root()
        data = str(root / "7scenes-redkitchen") if root is not None else None
    if data is None or not (data.startswith("synthetic") or Path(data).is_dir()):
        print(f"skipped: {data or '7-Scenes redkitchen under ../shared/data'} is not there (give DATA)",
              file=sys.stderr)
        return 0
    reference = map_of(recording(data, args.reference, cache_dir=args.cache_dir), args.reference)
    print(f"reference: lockstep at {args.reference}, every frame: {len(reference)} landmarks", flush=True)
    results = []
    for plan in args.plan:
        rec = recording(data, plan.letterbox, plan.precision, args.cache_dir)
        video_s = len(rec.detections) * (rec.detections[1].stamp - rec.detections[0].stamp)
        counts, rates, lost = [], [], Counter()
        for seed in range(args.seeds):
            rng = np.random.default_rng(seed)
            times = rng.lognormal(np.log(plan.detect_ms / 1e3), args.spread, size=len(rec.detections))
            detected = simulate(len(rec.detections), plan.every_n, plan.replicas, lambda f, t=times: float(t[f]),
                                args.frame_ms / 1e3)
            mapped = map_of(masked(rec, set(detected)), plan.letterbox)
            counts.append(len(mapped))
            rates.append(len(detected) / video_s)
            lost.update(missed_and_gained(reference, mapped)[0])
        enough = sum(c >= 0.9 * len(reference) for c in counts)
        row = {"plan": str(plan), "detections_per_s": [round(r, 1) for r in rates], "landmarks": counts,
               "median_landmarks": statistics.median(counts), "reference": len(reference),
               "runs_at_90pct": f"{enough}/{len(counts)}", "most_missed": lost.most_common(5)}
        results.append(row)
        print(f"{plan}: {statistics.median(rates):.1f} detections/s (median of {args.seeds}), landmarks "
              f"{' '.join(map(str, counts))} of {len(reference)}; >= 90 % in {enough}/{len(counts)}; missed most: "
              + ", ".join(f"{k} x{n}" for k, n in lost.most_common(4)), flush=True)
    if args.json_out:
        args.json_out.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
