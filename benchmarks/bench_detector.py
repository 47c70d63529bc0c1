"""Detector latency on real 640x480 7-Scenes frames: ONNX YOLOv5s with 1 and 2 threads, plus the oracle.

Why: the pipeline's frame budget is set by detection; this measures what one detector replica costs per frame
end to end (letterbox, inference, decode, NMS), after a warm-up, with the frames already decoded in memory.
With --int8 it also builds an int8 copy (calibrated on other frames of the same sequence) and times it.
With --openvino it times the network alone (same letterboxed input, same resized fp32 model) in onnxruntime and in
OpenVINO's CPU runtime (`pip install openvino`; not a dependency: on the 2-core AVX2 EPYC it was slower, see
docs/PERFORMANCE.md); --input-size picks the letterbox (default 384x512, the real-time choice there).

    .venv/bin/python benchmarks/bench_detector.py [--frames 50] [--int8] [--openvino] [--json-out out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from semmap.algorithms.detector.onnx_detector import OnnxDetector  # noqa: E402
from semmap.algorithms.detector.oracle import OracleDetector  # noqa: E402
from semmap.datasets import find_data_root  # noqa: E402
from semmap.datasets.base import InstanceBox  # noqa: E402
from semmap.runtime.models.model_store import ModelMissingError, quantize_int8, require_model  # noqa: E402


def ort_version() -> str:
    import onnxruntime

    return onnxruntime.__version__


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def stats_ms(samples: list[float]) -> dict[str, float]:
    a = np.asarray(samples) * 1e3
    return {
        "p50_ms": round(float(np.percentile(a, 50)), 4),
        "p95_ms": round(float(np.percentile(a, 95)), 4),
        "mean_ms": round(float(a.mean()), 4),
        "n": int(a.size),
    }


def bench_onnx(model: Path, frames: list[np.ndarray], threads: int, warmup: int, spin: bool) -> dict[str, float]:
    det = OnnxDetector(model, threads=threads, spin=spin)
    for rgb in frames[:warmup]:
        det.detect(rgb)
    times, counts = [], []
    cpu0 = time.process_time()
    for rgb in frames:
        t0 = time.perf_counter()
        boxes = det.detect(rgb)
        times.append(time.perf_counter() - t0)
        counts.append(len(boxes))
    # CPU seconds of all threads per frame: barely moved by other processes, unlike wall-clock latency
    cpu_ms = (time.process_time() - cpu0) / len(frames) * 1e3
    return {
        **stats_ms(times),
        "cpu_ms_per_frame": round(cpu_ms, 2),
        "detections_per_frame": round(float(np.mean(counts)), 2),
    }


def bench_network_runtimes(model: Path, frames: list[np.ndarray], hw: tuple[int, int], threads: int,
                           warmup: int) -> dict[str, dict[str, float]]:
    """The network alone (no letterbox, decode or NMS) on the same blobs: onnxruntime vs OpenVINO, same model."""
    import onnx
    import onnxruntime as ort
    import openvino as ov

    from semmap.algorithms.detector.onnx_detector import letterbox
    from semmap.runtime.models.yolov5_convert import resize_input

    data = resize_input(onnx.load(str(model)), hw).SerializeToString()
    blobs = [cv2.dnn.blobFromImage(letterbox(rgb, hw)[0], scalefactor=1.0 / 255.0) for rgb in frames]
    so = ort.SessionOptions()
    so.intra_op_num_threads, so.inter_op_num_threads = threads, 1
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    session = ort.InferenceSession(data, so, providers=["CPUExecutionProvider"])
    name = session.get_inputs()[0].name
    with tempfile.TemporaryDirectory(prefix="semmap-ov-") as tmp:
        path = Path(tmp) / "model.onnx"
        path.write_bytes(data)
        compiled = ov.Core().compile_model(str(path), "CPU", {"PERFORMANCE_HINT": "LATENCY", "NUM_STREAMS": 1,
                                                               "INFERENCE_NUM_THREADS": threads})
    request = compiled.create_infer_request()
    runners = {"onnxruntime": lambda b: session.run(None, {name: b})[0],
               f"openvino {ov.__version__.split('-')[0]}": lambda b: request.infer({0: b})[0]}
    outputs, results = {}, {}
    for label, run in runners.items():
        for b in blobs[:warmup]:
            run(b)
        times, cpu0 = [], time.process_time()
        for b in blobs:
            t0 = time.perf_counter()
            run(b)
            times.append(time.perf_counter() - t0)
        cpu_ms = (time.process_time() - cpu0) / len(blobs) * 1e3
        results[label] = {**stats_ms(times), "cpu_ms_per_frame": round(cpu_ms, 2)}
        outputs[label] = np.asarray(run(blobs[0]))
    a, b = outputs.values()
    results["max_abs_output_difference"] = {"value": float(np.abs(a - b).max())}
    return results


def bench_oracle(n_frames: int = 1000, n_instances: int = 12) -> dict[str, float]:
    rng = np.random.default_rng(0)
    instances = []
    for i in range(n_instances):
        x, y = rng.uniform(0, 500), rng.uniform(0, 380)
        instances.append(InstanceBox(i, "chair", (x, y, x + 100, y + 80), 4000))
    oracle = OracleDetector(seed=1)
    for f in range(20):
        oracle.detect(f, instances, 640, 480)
    times = []
    for f in range(n_frames):
        t0 = time.perf_counter()
        oracle.detect(f, instances, 640, 480)
        times.append(time.perf_counter() - t0)
    return {**stats_ms(times), "instances_per_frame": n_instances}


def replica_throughput(replicas: int, scene: Path, frames: int = 200) -> float:
    """Frames detected per second by N replicas sharing a 10x real-time stream (one ORT thread each when N > 1)."""
    import subprocess

    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "semmap.cli", "run", str(scene), "--out", tmp, "--realtime", "--only", "detector",
               "--detectors", str(replicas), "--max-frames", str(frames), "--set", "run.speed=10", "--no-viz",
               "--quiet", "--set", f"detector.threads={2 if replicas == 1 else 1}"]
        subprocess.run(cmd, check=True, capture_output=True, env={**os.environ, "CI": "true"})
        stats = json.loads((Path(tmp) / "stats.json").read_text())
    # frames still queued when the stream ends are dropped, so this is the rate sustained during the stream
    return stats["frames"]["detected"] / (frames / (30.0 * 10))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=50, help="timed frames per configuration")
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--model", type=Path, default=None, help="ONNX model (default: the fetched YOLOv5s)")
    ap.add_argument("--int8", action="store_true", help="also build and time an int8 copy of the model")
    ap.add_argument("--threads", default="1,2", help="thread counts to time (default 1,2)")
    ap.add_argument("--spin", action="store_true", help="let ORT threads busy-wait (faster only on an idle CPU)")
    ap.add_argument("--replicas", default="", help="also measure replica throughput through the bus, e.g. 1,2")
    ap.add_argument("--openvino", action="store_true", help="also time the network in OpenVINO vs onnxruntime")
    ap.add_argument("--input-size", default="384x512", help="letterbox HxW for --openvino (default 384x512)")
    ap.add_argument("--json-out", type=Path, default=None)
    args = ap.parse_args(argv)

    root = find_data_root()
    scene = root / "7scenes-redkitchen" if root else None
    if scene is None or not scene.is_dir():
        print("no 7-Scenes frames: set SEMMAP_DATA or provide <project>/../shared/data", file=sys.stderr)
        return 2
    try:
        model = require_model(args.model)
    except ModelMissingError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    all_frames = sorted(scene.glob("frame-*.color.jpg"))
    step = max(1, len(all_frames) // args.frames)
    chosen = all_frames[::step][: args.frames]
    frames = [cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB) for p in chosen]

    models = {"fp32": model}
    tmp = tempfile.TemporaryDirectory(prefix="semmap-bench-")
    if args.int8:
        calib = [p for p in all_frames[step // 2 :: step * 2] if p not in chosen][:24]
        t0 = time.perf_counter()
        models["int8"] = quantize_int8(model, calib, Path(tmp.name) / "int8.onnx")
        print(f"int8 model built in {time.perf_counter() - t0:.1f} s from {len(calib)} frames", file=sys.stderr)

    results: dict[str, object] = {
        "machine": {"cpu": cpu_name(), "cores": os.cpu_count(), "onnxruntime": ort_version()},
        "load_avg_before": [round(v, 2) for v in os.getloadavg()],
        "frames": len(frames),
        "spin": args.spin,
        "frame_size": [int(frames[0].shape[1]), int(frames[0].shape[0])],
        "onnx": {},
    }
    for label, path in models.items():
        for threads in (int(t) for t in args.threads.split(",")):
            r = bench_onnx(path, frames, threads, args.warmup, args.spin)
            results["onnx"][f"{label}_threads{threads}"] = r  # type: ignore[index]
            print(f"onnx {label:4s} threads={threads}: p50 {r['p50_ms']:7.2f} ms  p95 {r['p95_ms']:7.2f} ms  "
                  f"mean {r['mean_ms']:7.2f} ms  cpu {r['cpu_ms_per_frame']:7.2f} ms/frame  "
                  f"({r['detections_per_frame']} detections/frame)")  # fmt: skip
    tmp.cleanup()
    if args.openvino:
        hw = tuple(int(v) for v in args.input_size.lower().split("x"))
        for threads in (int(t) for t in args.threads.split(",")):
            runtimes = bench_network_runtimes(model, frames, hw, threads, args.warmup)  # type: ignore[arg-type]
            results.setdefault("network_runtimes", {})[f"{args.input_size}_threads{threads}"] = runtimes  # type: ignore[union-attr]
            for label, r in runtimes.items():
                if "p50_ms" in r:
                    print(f"network {args.input_size} threads={threads} {label:22s}: p50 {r['p50_ms']:7.2f} ms  "
                          f"cpu {r['cpu_ms_per_frame']:7.2f} ms/frame")
            print(f"  outputs differ by at most {runtimes['max_abs_output_difference']['value']:.1e}")
    r = bench_oracle()
    results["oracle"] = r
    print(f"oracle: p50 {r['p50_ms'] * 1e3:.0f} us  p95 {r['p95_ms'] * 1e3:.0f} us per frame "
          f"({r['instances_per_frame']} instances)")  # fmt: skip
    results["load_avg_after"] = [round(v, 2) for v in os.getloadavg()]
    for n in [int(v) for v in args.replicas.split(",") if v]:
        fps = replica_throughput(n, scene)
        results.setdefault("replicas", {})[str(n)] = {"detected_fps": fps}  # type: ignore[union-attr]
        print(f"{n} replica(s) through Zenoh: {fps:.1f} frames detected per second")
    if args.json_out:
        args.json_out.parent.mkdir(parents=True, exist_ok=True)
        args.json_out.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
