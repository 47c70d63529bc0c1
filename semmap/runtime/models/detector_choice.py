"""Which detector configuration serves real time on this machine: chosen by measuring, cached per machine.

Why: int8 is ~2.3x faster than fp32 on a CPU with VNNI; on an AVX2-only one its 8-bit products saturate and its
detections disagree with fp32, unless its weights have 7 bits (int8w7), so no fixed default is right everywhere.
`measure_configs` times each configuration that could serve real time
(precision fp32/int8/int8w7 x intra-op threads x letterbox size) on real frames, scores each against fp32 at full
size (F1 of same-class IoU >= 0.5 matches, recall per class), and `choose` takes, among those that agree
(F1 >= AGREEMENT_F1), the most faithful one that keeps up with real time, else the fastest. The result is
cached as JSON beside the models (`detector_choice.json`; in `$SEMMAP_CHOICE_DIR` where set, as in the container
image), keyed by the CPU model, its SIMD flags, the core count and the onnxruntime version: another machine (or an
upgrade) measures again. `semmap models doctor` prints the table; `detector.precision: auto` in real time reads
the choice.
"""

from __future__ import annotations

import json
import logging
import math
import os
import platform
import queue
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from statistics import median
from typing import Any

from semmap.core import environment
from semmap.core.outputs import atomic_write_bytes
from semmap.runtime.models.model_store import QUANTIZED_FILES, default_model_path, get_model_dir

log = logging.getLogger(__name__)

CHOICE_FILENAME = "detector_choice.json"
CHOICE_VERSION = 5  # 2: with the layouts (replicas x threads) of the choice; 3: the most faithful that keeps up;
# 4: ties at the threshold counted again (a cache measured without them chose 640x480 on AVX2);
# 5: int8w7 (7-bit weights) among the candidates
AGREEMENT_F1 = 0.9  # the int8 rule: detections must agree with fp32 at full size
FAITHFUL_SHARE = 0.5  # `choose`: the most faithful configuration that still detects every 2nd frame in real time
FRONT_END_KEEPS_UP = 0.9  # `setup_plan`: replicas only where the odometry posed this share of a real-time run
TIE_MARGIN = 0.1  # scores this close below the confidence threshold are ties, not disagreements (`agreement`)
IOU_MATCH = 0.5
FULL_HW = (480, 640)
# letterbox sizes (h, w) tried; 4:3 frames fill 512x384 and 416x320 without padding, 640x384 pads the sides
SIZES: tuple[tuple[int, int], ...] = ((480, 640), (384, 640), (384, 512), (352, 480), (320, 416))
# SIMD features that decide what int8 and fp32 cost (the key of the cache)
KEY_FLAGS = ("avx", "avx2", "fma", "f16c", "avx512f", "avx512bw", "avx512vl", "avx512_vnni", "avx512_bf16",
             "avx_vnni", "amx_int8", "amx_bf16", "asimd", "asimddp", "i8mm", "sve")  # fmt: skip
SMALL_CLASSES = ("cup", "book", "bottle", "mouse", "cell phone", "remote")


# ----------------------------------------------------------------------------------------------------------
# The machine


def _cpuinfo() -> tuple[str, set[str]]:
    model, flags = "", set()
    try:
        text = Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace")
    except OSError:
        return platform.processor() or platform.machine(), flags
    for line in text.splitlines():
        key, _, value = line.partition(":")
        key = key.strip().lower()
        if key in ("model name", "cpu model", "hardware") and not model:
            model = value.strip()
        elif key in ("flags", "features") and not flags:
            flags = set(value.split())
    return model or platform.processor() or platform.machine(), flags


def hardware_key() -> dict[str, Any]:
    """What the measurement depends on: CPU model, its SIMD flags, the cores this process may use, onnxruntime."""
    import onnxruntime as ort

    model, flags = _cpuinfo()
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return {
        "cpu": model,
        "flags": sorted(f for f in KEY_FLAGS if f in flags),
        "cores": cores,
        "onnxruntime": ort.__version__,
        "providers": sorted(ort.get_available_providers()),
    }


def has_vnni(key: dict[str, Any]) -> bool:
    return any(f in key.get("flags", ()) for f in ("avx512_vnni", "avx_vnni", "amx_int8", "asimddp"))


# ----------------------------------------------------------------------------------------------------------
# Configurations and their agreement


@dataclass(frozen=True)
class DetectorConfigChoice:
    """One way to run the detector: which copy of the model, how many threads, which letterbox."""

    precision: str  # fp32 | int8 | int8w7
    threads: int
    height: int
    width: int

    @property
    def hw(self) -> tuple[int, int]:
        return (self.height, self.width)

    def label(self) -> str:
        return f"{self.precision} {self.width}x{self.height} {self.threads}t"


@dataclass
class Measured:
    config: DetectorConfigChoice
    p50_ms: float
    p90_ms: float
    cpu_ms: float  # process CPU time per frame (what it takes from the services sharing the cores)
    f1: float  # with TIE_MARGIN: the gate
    recall: float
    precision: float
    recall_per_class: dict[str, float] = field(default_factory=dict)
    f1_strict: float = 0.0  # without the margin (both at the confidence threshold): reported
    min_ms: float = 0.0  # fastest frame: the cost alone on a machine shared with others (timeit's convention)

    @property
    def alone_ms(self) -> float:
        """Latency alone: the fastest frame, or its CPU time over its threads where that is less (other programs
        on a shared machine stretch wall times, hardly CPU times)."""
        wall = self.min_ms or self.p50_ms
        return min(wall, self.cpu_ms / max(1, self.config.threads)) if self.cpu_ms > 0 else wall

    @property
    def agrees(self) -> bool:
        return self.f1 >= AGREEMENT_F1

    @property
    def small_object_recall(self) -> dict[str, float]:
        """Recall of the classes small in the frame (`SMALL_CLASSES`): what a smaller letterbox loses first."""
        return {c: r for c, r in sorted(self.recall_per_class.items()) if c in SMALL_CLASSES}

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["config"] = asdict(self.config)
        d["agrees"] = self.agrees
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Measured:
        d = {k: v for k, v in d.items() if k != "agrees"}
        return cls(**{**d, "config": DetectorConfigChoice(**d["config"])})


def _iou(a: Any, b: Any) -> float:
    w = max(0.0, min(a.x2, b.x2) - max(a.x1, b.x1))
    h = max(0.0, min(a.y2, b.y2) - max(a.y1, b.y1))
    inter = w * h
    union = (a.x2 - a.x1) * (a.y2 - a.y1) + (b.x2 - b.x1) * (b.y2 - b.y1) - inter
    return inter / union if union > 0 else 0.0


def match(ref: Sequence[Any], other: Sequence[Any]) -> list[int]:
    """Indices of `ref` boxes matched one-to-one (same class, IoU >= 0.5, best pairs first) by `other`."""
    pairs = sorted(
        ((_iou(a, b), i, j) for i, a in enumerate(ref) for j, b in enumerate(other) if a.class_name == b.class_name),
        reverse=True,
    )
    used_a: set[int] = set()
    used_b: set[int] = set()
    for value, i, j in pairs:
        if value < IOU_MATCH:
            break
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
    return sorted(used_a)


def agreement(
    ref: Sequence[Sequence[Any]], out: Sequence[Sequence[Any]], conf: float = 0.4, margin: float = 0.0
) -> tuple[float, float, float, dict[str, float]]:
    """(F1, recall, precision, recall per class) of detections `out` against reference `ref`, frame by frame.

    Boxes scored at or above `conf` count; with a `margin`, a box may be matched by one the other model scored
    down to `conf - margin` (both lists must then hold boxes down to that score): a box that one model scores 0.41
    and the other 0.39 is a tie at the threshold, not a disagreement.
    """
    floor = conf - margin
    ref_hi = [[b for b in r if b.score >= conf] for r in ref]
    out_hi = [[b for b in o if b.score >= conf] for o in out]
    ref_lo = [[b for b in r if b.score >= floor] for r in ref]
    out_lo = [[b for b in o if b.score >= floor] for o in out]
    n_ref = sum(len(r) for r in ref_hi)
    n_out = sum(len(o) for o in out_hi)
    per_class_ref: dict[str, int] = {}
    per_class_hit: dict[str, int] = {}
    found = kept = 0
    for r_hi, o_lo, r_lo, o_hi in zip(ref_hi, out_lo, ref_lo, out_hi, strict=True):
        matched = set(match(r_hi, o_lo))
        found += len(matched)
        kept += len(match(o_hi, r_lo))
        for i, box in enumerate(r_hi):
            per_class_ref[box.class_name] = per_class_ref.get(box.class_name, 0) + 1
            per_class_hit[box.class_name] = per_class_hit.get(box.class_name, 0) + (i in matched)
    recall = found / n_ref if n_ref else 1.0
    precision = kept / n_out if n_out else (1.0 if n_ref == 0 else 0.0)
    f1 = 2 * recall * precision / (recall + precision) if recall + precision > 0 else 0.0
    per_class = {c: per_class_hit[c] / n for c, n in sorted(per_class_ref.items())}
    return f1, recall, precision, per_class


def choose(rows: Sequence[Measured], cores: int, fps: float = 30.0, others: float | None = None) -> Measured | None:
    """Among the configurations whose detections agree with fp32 at full size: the most faithful one (F1 against
    it) that still detects at least `FAITHFUL_SHARE` of the frames of a real-time run, else the one that detects
    most often (`rank_for_realtime`: its CPU time over the cores the other services leave, or its latency).

    Why not simply the fastest: a smaller letterbox that agrees by the F1 rule still loses what is small and far
    (a laptop 3 m away, one half of a long table). Where the machine can afford the full frame often enough (int8
    with VNNI: 21 detections a second at 640x480), the fastest would trade those objects for detections the map
    does not need: every 3rd frame at 640x480 maps what every frame does (lockstep, 7-Scenes), every 2nd leaves
    real time's uneven cadence a margin. On an AVX2-only CPU nothing at full size gets there, and the fastest wins
    as before. `others`: the other services' CPU per frame (default: `gt`'s estimate, what the doctor plans for;
    a run re-chooses with its front end's cost, `for_front_end`)."""
    others = DEFAULT_OTHERS_CPU_MS["gt"] if others is None else others
    ranked = rank_for_realtime(rows, cores, fps, others)
    if not ranked:
        return None
    often = [r for r in ranked if 1e3 / plan_cadence(r, cores, fps, others).interval_ms >= FAITHFUL_SHARE * fps]
    return max(often, key=lambda r: round(r.f1, 2)) if often else ranked[0]  # (ties: the faster, ranked first)


# ----------------------------------------------------------------------------------------------------------
# Measuring


def available_precisions(model_dir: Path) -> list[str]:
    """fp32, and each quantised copy `semmap models quantize` left in `model_dir`."""
    return ["fp32", *(p for p, name in QUANTIZED_FILES.items() if (model_dir / name).is_file())]


def candidate_configs(
    precisions: Sequence[str], cores: int, sizes: Sequence[tuple[int, int]] = SIZES
) -> list[DetectorConfigChoice]:
    threads = sorted({1, min(2, max(1, cores))})
    return [DetectorConfigChoice(p, t, h, w) for p in precisions for (h, w) in sizes for t in threads]


def model_bytes(precision: str, hw: tuple[int, int], model_dir: Path | None = None) -> bytes:
    """The packaged model of `precision` with its input resized to `hw` (serialized ONNX, built in memory)."""
    import onnx

    from semmap.runtime.models.model_store import packaged_model
    from semmap.runtime.models.yolov5_convert import resize_input

    directory = Path(model_dir) if model_dir is not None else get_model_dir()
    path = default_model_path(directory) if precision == "fp32" else directory / QUANTIZED_FILES[precision]
    if not path.is_file():
        path = packaged_model(precision)  # raises the usual "fetch"/"quantize" hint
    model = onnx.load(str(path))
    return resize_input(model, hw).SerializeToString()


def detections_down_to(detector: Any, images: Sequence[Any], floor: float) -> list[list[Any]]:
    """Every image's boxes down to the score `floor` (the detector's own threshold is restored after), so that
    `agreement` can tell a tie at the threshold from a disagreement."""
    conf = detector.conf
    detector.conf = floor
    try:
        return [detector.detect(img) for img in images]
    finally:
        detector.conf = conf


def format_recall(recall: dict[str, float]) -> str:
    """'book 0.89, cup 1.00': recall per class, as the doctor's table and a real-time run print it."""
    return ", ".join(f"{c} {r:.2f}" for c, r in recall.items())


def measure_configs(
    images: Sequence[Any],
    configs: Sequence[DetectorConfigChoice],
    timing_frames: int = 12,
    conf: float = 0.4,
    iou: float = 0.45,
    model_dir: Path | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[Measured]:
    """Time each configuration on `images` (RGB uint8 arrays) and score it against fp32 at full size."""
    from semmap.algorithms.detector.onnx_detector import OnnxDetector

    def detector(c: DetectorConfigChoice, blob: bytes) -> OnnxDetector:
        return OnnxDetector(blob, conf=conf, iou=iou, threads=c.threads)

    def low(det: OnnxDetector) -> list[Any]:
        return detections_down_to(det, images, conf - TIE_MARGIN)

    blobs: dict[tuple[str, tuple[int, int]], bytes] = {}
    outputs: dict[tuple[str, tuple[int, int]], list[Any]] = {}
    ref_cfg = DetectorConfigChoice("fp32", max(c.threads for c in configs), *FULL_HW)
    ref_key = ("fp32", FULL_HW)
    blobs[ref_key] = model_bytes("fp32", FULL_HW, model_dir)
    ref_det = detector(ref_cfg, blobs[ref_key])
    outputs[ref_key] = low(ref_det)
    del ref_det
    rows = []
    timing = list(images[: max(1, timing_frames)])
    for c in configs:
        key = (c.precision, c.hw)
        if key not in blobs:
            blobs[key] = model_bytes(c.precision, c.hw, model_dir)
        det = detector(c, blobs[key])
        det.detect(timing[0])  # warm-up: first-run allocations
        wall = []
        cpu0 = time.process_time()
        for img in timing:
            t0 = time.perf_counter()
            det.detect(img)
            wall.append((time.perf_counter() - t0) * 1e3)
        cpu_ms = (time.process_time() - cpu0) * 1e3 / len(timing)
        if key not in outputs:
            outputs[key] = low(det)
        f1, rec, prec, per_class = agreement(outputs[ref_key], outputs[key], conf, TIE_MARGIN)
        strict = agreement(outputs[ref_key], outputs[key], conf, 0.0)[0]
        wall.sort()
        row = Measured(c, wall[len(wall) // 2], wall[min(len(wall) - 1, int(0.9 * len(wall)))], cpu_ms, f1, rec,
                       prec, per_class, strict, wall[0])  # fmt: skip
        rows.append(row)
        if progress is not None:
            progress(f"{c.label():>18}: {row.p50_ms:6.1f} ms p50, F1 {row.f1:.2f}")
    return rows


# ----------------------------------------------------------------------------------------------------------
# Layouts: one detector with several threads, or several single-thread replicas, beside the others' load

LAYOUT_SECONDS = 6.0  # timed per layout, after every process has loaded its model and warmed up
MAX_REPLICAS = 2  # each replica holds its own copy of the network (~350 MB resident with YOLOv5s)
BURN_PERIOD_S = 1.0 / 30.0  # the other services work once a frame


@dataclass(frozen=True)
class Layout:
    """`replicas` detector processes of `threads` intra-op threads each, and what they achieved together while a
    stand-in for the other services (`load_cores` of CPU, spread over every core) ran beside them."""

    replicas: int
    threads: int
    detections_per_s: float
    load_cores: float

    def label(self) -> str:
        return f"{self.replicas} x {self.threads} thread{'s' if self.threads != 1 else ''}"


def candidate_layouts(cores: int) -> list[tuple[int, int]]:
    """(replicas, threads): the single detector as `candidate_configs` times it, and single-thread replicas."""
    layouts = [(1, min(2, max(1, cores)))]
    if cores >= 2:
        layouts.append((min(MAX_REPLICAS, cores), 1))
    return layouts


def burn(share: float, start: Any, seconds: float) -> None:
    """A child process: a stand-in load, busy `share` of every `BURN_PERIOD_S` for `seconds` once `start` is set
    (`measure_layouts`'s other services; benchmarks/bench_realtime.py's slower cores)."""
    start.wait()
    stop = time.monotonic() + seconds
    while time.monotonic() < stop:
        t0 = time.monotonic()
        while time.monotonic() - t0 < share * BURN_PERIOD_S:
            pass
        time.sleep(BURN_PERIOD_S * (1.0 - share))


def _detect_flat_out(blob: bytes, threads: int, images: list[Any], start: Any, seconds: float, out: Any) -> None:
    from semmap.algorithms.detector.onnx_detector import OnnxDetector  # a child process: one replica

    det = OnnxDetector(blob, threads=threads)
    det.detect(images[0])
    out.put("ready")
    start.wait()
    count, stop = 0, time.monotonic() + seconds
    while time.monotonic() < stop:
        det.detect(images[count % len(images)])
        count += 1
    out.put(count)


def measure_layouts(blob: bytes, images: Sequence[Any], cores: int, load_cores: float,
                    seconds: float = LAYOUT_SECONDS) -> list[Layout]:  # fmt: skip
    """Detections per second of each layout of the model `blob` (serialized ONNX: the chosen precision and
    letterbox, `model_bytes`), flat out, while `load_cores` of CPU burn
    beside it in short duty cycles (the other services of a real-time run, as `record_pipeline_cost` measured them).

    Why: an intra-op thread pool waits at every operator for its slowest thread, so when the other services take
    a core from it now and then, both threads stall; single-thread replicas do not wait for each other. On the
    2-core AVX2 EPYC a real-time 7-Scenes run detected 10.8 frames a second with one 2-thread detector and 12.9
    with two 1-thread replicas, where the cost model (CPU time over free cores) predicts the same for both: only a
    measurement tells them apart, and it differs by machine."""
    import multiprocessing

    ctx = multiprocessing.get_context("spawn")  # (onnxruntime's thread pools do not survive a fork)
    frames = list(images[: max(1, min(8, len(images)))])
    share = min(1.0, max(0.0, load_cores / max(1, cores)))
    layouts = []
    for replicas, threads in candidate_layouts(cores):
        start, out = ctx.Event(), ctx.Queue()
        workers = [ctx.Process(target=_detect_flat_out, args=(blob, threads, frames, start, seconds, out),
                               daemon=True) for _ in range(replicas)]  # fmt: skip
        burners = [ctx.Process(target=burn, args=(share, start, seconds + 0.5), daemon=True)
                   for _ in range(cores if share > 0 else 0)]  # fmt: skip
        for proc in workers + burners:
            proc.start()
        try:
            ready = [out.get(timeout=120.0) for _ in workers]
            assert ready == ["ready"] * replicas
            start.set()
            count = sum(int(out.get(timeout=seconds + 120.0)) for _ in workers)
        finally:
            for proc in workers + burners:
                proc.join(timeout=seconds + 5.0)
                if proc.is_alive():
                    proc.kill()
        layouts.append(Layout(replicas, threads, count / seconds, round(load_cores, 2)))
    return layouts


def best_layout(layouts: Sequence[Layout]) -> Layout | None:
    """The layout that detected most often; replicas only where they beat the single detector by 5 % (each costs
    its memory)."""
    single = [lay for lay in layouts if lay.replicas == 1]
    if not single:
        return None
    best = max(layouts, key=lambda lay: lay.detections_per_s)
    return best if best.detections_per_s > 1.05 * single[0].detections_per_s else single[0]


def calibration_images(source: str | Path | None, count: int = 24) -> tuple[list[Any], str]:
    """`count` RGB frames evenly spread over a dataset (7-Scenes under ../shared/data when none is given and it is
    there, else the synthetic scene); returns (images, where they came from)."""
    import numpy as np

    from semmap.datasets import find_data_root, open_dataset

    if source is None:
        root = find_data_root()
        seven = root / "7scenes-redkitchen" if root is not None else None
        source = seven if seven is not None and seven.is_dir() else f"synthetic:frames={count * 4}"
    dataset = open_dataset(source)
    idx = np.linspace(0, len(dataset) - 1, min(count, len(dataset))).astype(int)
    return [dataset[int(i)].rgb for i in idx], str(source)


# ----------------------------------------------------------------------------------------------------------
# The cache


def choice_path(model_dir: Path | None = None) -> Path:
    """Where this machine's measurement is kept: beside the models of `model_dir` where one is given (`--dir`),
    else in `$SEMMAP_CHOICE_DIR`, else beside the models (`$SEMMAP_MODEL_DIR`). Why a directory of its own: a
    container's models belong to root and its services run as another user, so the measurement needs a writable
    home (a volume) that a rebuilt image's models do not share."""
    if model_dir is not None:
        return Path(model_dir) / CHOICE_FILENAME
    own = environment.read(environment.CHOICE_DIR)
    return (Path(own).expanduser() if own else get_model_dir()) / CHOICE_FILENAME


def writable_choice_home(model_dir: Path | None = None) -> Path:
    """The directory `choice_path` names, made if missing; OSError where this user cannot write there. Checked
    before measuring (`measure_and_save`), so a read-only home fails at once, not after a minute of timing."""
    home = choice_path(model_dir).parent
    try:
        home.mkdir(parents=True, exist_ok=True)
        writable = os.access(home, os.W_OK)
    except OSError:
        writable = False
    if not writable:
        raise OSError(f"cannot keep this machine's measurement in {home} (not writable): set SEMMAP_CHOICE_DIR to a "
                      "directory of yours")  # fmt: skip
    return home


def save_choice(rows: Sequence[Measured], key: dict[str, Any], source: str, model_dir: Path | None = None,
                layouts: Sequence[Layout] = ()) -> Path:  # fmt: skip
    best = choose(rows, int(key.get("cores", 1)))
    doc = {
        "version": CHOICE_VERSION,
        "key": key,
        "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "load_average": [round(v, 2) for v in os.getloadavg()] if hasattr(os, "getloadavg") else None,
        "frames": source,
        "rule": f"F1 >= {AGREEMENT_F1} against fp32 {FULL_HW[1]}x{FULL_HW[0]} (ties within {TIE_MARGIN} of the "
        "confidence threshold count as agreement), then the most faithful (F1) that detects at least "
        f"{FAITHFUL_SHARE:g} of the frames of a 30 fps run, else the shortest time per detection in a real-time run",
        "rows": [r.to_dict() for r in rows],
        "choice": best.to_dict() if best is not None else None,
        "layouts": [asdict(lay) for lay in layouts],  # of the choice (`measure_layouts`)
    }
    before = load_choice(model_dir, key)  # the same machine measured again: keep what its runs measured
    for kept in ("pipeline_cpu_ms_per_frame", "pipeline_cpu_ms_runs", "achieved_detections_per_s"):
        if before and before.get(kept):
            doc[kept] = before[kept]
    path = choice_path(model_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, (json.dumps(doc, indent=1) + "\n").encode())
    return path


def load_choice(model_dir: Path | None = None, key: dict[str, Any] | None = None) -> dict[str, Any] | None:
    """The cached measurement if it was made on this machine (same key), else None (measure again)."""
    path = choice_path(model_dir)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("version") != CHOICE_VERSION:
        return None
    if doc.get("key") != (key if key is not None else hardware_key()):
        return None
    return doc


def cached_choice(model_dir: Path | None = None, key: dict[str, Any] | None = None) -> Measured | None:
    doc = load_choice(model_dir, key)
    if doc is None or not doc.get("choice"):
        return None
    return Measured.from_dict(doc["choice"])


def measure_and_save(
    source: str | Path | None = None,
    frames: int = 48,
    model_dir: Path | None = None,
    sizes: Sequence[tuple[int, int]] = SIZES,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Measure every candidate on this machine and cache the result; returns the cached document."""
    writable_choice_home(model_dir)
    key = hardware_key()
    directory = Path(model_dir) if model_dir is not None else get_model_dir()
    images, where = calibration_images(source, frames)
    configs = candidate_configs(available_precisions(directory), int(key["cores"]), sizes)
    rows = measure_configs(images, configs, model_dir=directory, progress=progress)
    best = choose(rows, int(key["cores"]))
    layouts: list[Layout] = []
    if best is not None and int(key["cores"]) >= 2:
        before = load_choice(model_dir, key)
        load = others_cpu_ms("gt", before)[0] * 30.0 / 1e3  # the others' cores in a 30 fps run
        blob = model_bytes(best.config.precision, best.config.hw, directory)
        try:
            layouts = measure_layouts(blob, images, int(key["cores"]), load)
        except (queue.Empty, AssertionError, OSError, RuntimeError, ValueError) as exc:  # a replica died or hung
            log.warning("detector layouts not measured (%s: %s): real time keeps one detector", type(exc).__name__,
                        exc)
        if progress is not None:
            for lay in layouts:
                progress(f"{best.config.label()} as {lay.label()}: {lay.detections_per_s:.1f} detections/s "
                         f"beside {lay.load_cores:.2f} cores of load")
    save_choice(rows, key, where, model_dir, layouts)
    doc = load_choice(model_dir, key)
    assert doc is not None
    return doc


def format_table(doc: dict[str, Any]) -> str:
    """The measured configurations as a text table, fastest first, and the choice."""
    key = doc["key"]
    lines = [
        f"machine: {key['cpu']}, {key['cores']} cores, flags {' '.join(key['flags']) or '-'}"
        f" ({'VNNI' if has_vnni(key) else 'no VNNI'}), onnxruntime {key['onnxruntime']}",
        f"measured {doc['measured_at']} (load average {doc.get('load_average')}) on {doc['frames']}",
        f"rule: {doc['rule']}",
        f"{'config':<20} {'min ms':>7} {'p50 ms':>7} {'cpu ms':>7} {'in run':>7} {'F1':>5} {'strict':>6} "
        f"{'recall':>6}  small-object recall",
    ]
    cores = int(key.get("cores", 1))
    others, _ = others_cpu_ms("gt", doc)

    def in_run(r: Measured) -> float:
        return plan_cadence(r, cores, 30.0, others).interval_ms

    rows = sorted((Measured.from_dict(r) for r in doc["rows"]), key=in_run)
    for r in rows:
        small = format_recall(r.small_object_recall)
        mark = "" if r.agrees else "  (disagrees)"
        lines.append(f"{r.config.label():<20} {r.alone_ms:7.1f} {r.p50_ms:7.1f} {r.cpu_ms:7.1f} {in_run(r):7.1f} "
                     f"{r.f1:5.2f} {r.f1_strict:6.2f} {r.recall:6.2f}  {small}{mark}")  # fmt: skip
    lines.append(f"(in run: expected ms per detection in a real-time run at 30 fps, the other services taking "
                 f"{others:.0f} ms of CPU per frame of the {cores} cores)")
    best = doc.get("choice")
    layouts = [Layout(**d) for d in doc.get("layouts") or []]
    if best and layouts:
        lines.append(f"{Measured.from_dict(best).config.label()} flat out beside {layouts[0].load_cores:.2f} cores "
                     "of stand-in load (the other services of a 30 fps run): "
                     + ", ".join(f"{lay.label()} {lay.detections_per_s:.1f} detections/s" for lay in layouts))
    if best:
        lines.append(f"choice (detector.precision auto, real time): {Measured.from_dict(best).config.label()}"
                     + (f", {chosen.label()}" if (chosen := best_layout(layouts)) is not None else ""))
    else:
        lines.append("choice: none agrees with fp32; real time runs fp32 at full size")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------------------
# The frame budget: how often the detector can run while the other services share the cores

# CPU the other services of a real-time run take per frame of video (player, odometry, tracker, associator,
# backend, viewer), used until a run on this machine has measured it (then `record_pipeline_cost` keeps the
# figure in the cache, per odometry mode). Measured on a 2-core AMD EPYC at 30 fps: `gt` and `rgbd` on 7-Scenes;
# `orbslam3` 47-53 ms on Bonn crowd and 7-Scenes. Why a figure per front end: planned with the 40 ms fallback, a
# first ORB-SLAM3 run on Bonn crowd gave the detector fp32 every 3rd frame, 2.04 cores were asked of 2, and the
# front end posed 85 % of the frames (0.14 m); planned with its own cost, int8 every 2nd frame: 91-92 %, 0.07 m.
DEFAULT_OTHERS_CPU_MS = {"gt": 30.0, "rgbd": 40.0, "orbslam3": 48.0}
DEFAULT_OTHERS_FALLBACK_MS = 40.0
MIN_FREE_CORES = 0.25
RUNS_REMEMBERED = 5  # real-time runs whose measured costs the next plan takes the median of


@dataclass(frozen=True)
class CadencePlan:
    """What real time will achieve: a detection at most every `interval_ms` of video."""

    detect_alone_ms: float  # latency alone (the measurement)
    interval_ms: float  # expected time per detection inside the pipeline
    free_cores: float  # cores left to the detector by the other services
    others_cpu_ms: float  # the other services' CPU per frame of video
    fps: float
    threads: int = 1
    replicas: int = 1  # detector processes sharing the frames by rank (`measure_layouts`)
    layout_note: str = ""  # why this many replicas: what `measure_layouts` measured

    @property
    def flat_out(self) -> bool:
        """Its threads fit in the cores the others leave: it may take the next frame as soon as it is free (its
        queue keeps the newest) without starving them. Otherwise its cadence is held to its share. Replicas chosen
        by `measure_layouts` were measured flat out beside the others' load: they take their frames flat out."""
        return self.replicas > 1 or self.threads <= self.free_cores

    @property
    def every_n(self) -> int:
        ratio = self.interval_ms * self.fps / 1e3  # frames of video per detection
        if self.replicas > 1:
            # replicas take turns by blocks of every_n frames (semmap/algorithms/detector/turns.py), each detecting
            # the first frame of its block it can: the nearest whole number of frames per detection of them all. At
            # every frame two replicas that each need two frames' time fall into step and detect frames n and n+1,
            # then none for three (measured: one distinct view per 0.13 s where turns give one per 0.07 s)
            return max(1, math.floor(ratio + 0.5))
        if self.flat_out:
            return max(1, math.floor(ratio + 0.05))
        return max(1, math.ceil(ratio - 0.05))  # (a 5 % slack: the next frame is close)

    @property
    def detections_per_s(self) -> float:
        return min(self.fps / self.every_n, 1e3 / self.interval_ms)

    def to_dict(self) -> dict[str, float]:
        return {"detect_alone_ms": round(self.detect_alone_ms, 1), "interval_ms": round(self.interval_ms, 1),
                "free_cores": round(self.free_cores, 2), "others_cpu_ms_per_frame": round(self.others_cpu_ms, 1),
                "fps": self.fps, "every_n_frames": self.every_n, "replicas": self.replicas, "threads": self.threads,
                "expected_detections_per_s": round(self.detections_per_s, 2)}  # fmt: skip


def plan_cadence(row: Measured, cores: int, fps: float, others_cpu_ms: float) -> CadencePlan:
    """The detector's time per frame inside a real-time run: its CPU time spread over the cores the others leave
    (cores - their CPU per second), never less than its latency alone."""
    others_cores = others_cpu_ms * fps / 1e3
    free = max(MIN_FREE_CORES, float(cores) - others_cores)
    interval = max(row.alone_ms, row.cpu_ms / min(float(row.config.threads), free))
    return CadencePlan(row.alone_ms, interval, free, others_cpu_ms, fps, row.config.threads)


def last_achieved(odometry: str, detector: str, model_dir: Path | None = None) -> float | None:
    """Detections per second of video the last real-time run here achieved with this odometry and detector."""
    doc = load_choice(model_dir) or {}
    return (doc.get("achieved_detections_per_s") or {}).get(f"{odometry.split(':', 1)[0]} {detector}")


def others_cpu_ms(odometry: str, doc: dict[str, Any] | None) -> tuple[float, str]:
    """(CPU ms per frame the other services take, where the figure comes from) for this odometry mode."""
    mode = odometry.split(":", 1)[0]
    measured = (doc or {}).get("pipeline_cpu_ms_per_frame", {}).get(mode)
    if measured:
        return float(measured), "measured by the last real-time run here"
    return DEFAULT_OTHERS_CPU_MS.get(mode, DEFAULT_OTHERS_FALLBACK_MS), "default estimate"


def record_pipeline_cost(odometry: str, cpu_ms_per_frame: float, model_dir: Path | None = None,
                         detector: str = "", detections_per_s: float = 0.0, speed: float = 1.0,
                         front_end_share: float | None = None) -> bool:  # fmt: skip
    """Keep the other services' CPU per frame measured by a real-time run (only in this machine's cache), and what
    the run's detector (`detector`: its label) achieved, shown beside the next plan's expectation. Not from a run
    played faster than its recording (`run.speed`, e.g. the 3x soak): its services drop frames and load the cores
    differently, so its figures would mislead the next plan at the recording's own speed. `front_end_share`: the
    share of the frames the odometry posed (`replica_plan` reads it).

    The plan reads the CPU cost as the median of the last `RUNS_REMEMBERED` runs, not the last one's: it moves with the
    machine's load and with ORB-SLAM3's luck (Bonn crowd: 47-53 ms a frame in runs one after another), and a plan
    that follows each run picks another detector for the next (int8 640x480 after one run, int8w7 512x384 after
    the next), which makes runs of the same recording incomparable."""
    doc = load_choice(model_dir)
    if doc is None or cpu_ms_per_frame <= 0 or speed != 1.0:
        return False
    mode = odometry.split(":", 1)[0]
    runs = doc.setdefault("pipeline_cpu_ms_runs", {}).setdefault(mode, [])
    runs.append(round(cpu_ms_per_frame, 1))
    del runs[:-RUNS_REMEMBERED]
    doc.setdefault("pipeline_cpu_ms_per_frame", {})[mode] = float(median(runs))
    if front_end_share is not None:  # (the last run's: where it starved the front end, `replica_plan` holds back)
        doc.setdefault("front_end_posed_share", {})[mode] = round(front_end_share, 3)
    if detector and detections_per_s > 0:
        doc.setdefault("achieved_detections_per_s", {})[f"{mode} {detector}"] = round(detections_per_s, 2)
    atomic_write_bytes(choice_path(model_dir), (json.dumps(doc, indent=1) + "\n").encode())
    return True


def rank_for_realtime(rows: Sequence[Measured], cores: int, fps: float = 30.0,
                      others: float = DEFAULT_OTHERS_CPU_MS["gt"]) -> list[Measured]:
    """Agreeing configurations, best for real time first: shortest time per detection inside the pipeline."""
    ok = [r for r in rows if r.agrees]
    return sorted(ok, key=lambda r: (plan_cadence(r, cores, fps, others).interval_ms, r.alone_ms))


# ----------------------------------------------------------------------------------------------------------
# What a detector of a run uses


MEASURED_HERE = "measured on this machine"
MEASURED_FOR_FRONT_END = "measured on this machine, chosen for the front end's cost"


@dataclass(frozen=True)
class DetectorSetup:
    """How the detector of a run is built, and why."""

    precision: str
    threads: int
    hw: tuple[int, int] | None  # letterbox (h, w); None: the model's own input size
    origin: str  # "measured on this machine" | "set" | "not measured here: ..."
    measured: Measured | None = None  # the cached row of this configuration, if there is one

    def label(self) -> str:
        size = f"{self.hw[1]}x{self.hw[0]}" if self.hw else "model size"
        return f"{self.precision} {size} {self.threads} thread{'s' if self.threads != 1 else ''}"


def parse_size(text: str) -> tuple[int, int] | None:
    """'512x384' (W x H) -> (384, 512) (h, w); 'auto' -> None."""
    if text == "auto":
        return None
    w, _, h = text.partition("x")
    hw = (int(h), int(w))
    if hw[0] % 32 or hw[1] % 32:
        raise ValueError(f"detector.input_size {text}: both sides must be multiples of 32")
    return hw


def resolve_setup(precision: str, threads: int, input_size: str, realtime: bool,
                  model_dir: Path | None = None) -> DetectorSetup:  # fmt: skip
    """The detector configuration of a run. `auto` precision in real time takes this machine's measured choice
    (`semmap models doctor`); where nothing was measured here, fp32 at full size (int8 only gains on CPUs with
    VNNI, and nothing says this one has it). Explicit settings win; lockstep is fp32 at full size (its figures
    are fp32's)."""
    hw = parse_size(input_size)
    if precision == "auto" and realtime:
        doc = load_choice(model_dir)
        best = Measured.from_dict(doc["choice"]) if doc and doc.get("choice") else None
        if best is not None:
            c = best.config
            return DetectorSetup(c.precision, threads or c.threads, hw or (c.height, c.width),
                                 MEASURED_HERE if not threads else "measured on this machine, threads set",
                                 best)  # fmt: skip
        return DetectorSetup("fp32", threads or 2, hw, "not measured on this machine (`semmap models doctor`)")
    fixed = "fp32" if precision == "auto" else precision
    row = None
    doc = load_choice(model_dir) if realtime else None
    for r in (doc or {}).get("rows", []):
        m = Measured.from_dict(r)
        if (m.config.precision, m.config.threads, m.config.hw) == (fixed, threads or 2, hw or FULL_HW):
            row = m
    return DetectorSetup(fixed, threads or 2, hw, "set" if precision != "auto" else "lockstep", row)


def setup_plan(setup: DetectorSetup, fps: float, odometry: str, model_dir: Path | None = None,
               cores: int | None = None, replicas: bool = False,
               replicas_set: int = 1) -> tuple[CadencePlan | None, str]:  # fmt: skip
    """The real-time cadence for `setup` (None when its cost was never measured here) and where the other
    services' cost comes from; replicas=True: single-thread replicas where this machine measured them better
    (`replica_plan`); replicas_set > 1: that many replicas set by hand (`--detectors N`), taking turns
    (`replicas_by_hand`)."""
    if setup.measured is None:
        return None, ""
    doc = load_choice(model_dir)
    others, source = others_cpu_ms(odometry, doc)
    n = cores if cores is not None else int((doc or {}).get("key", {}).get("cores") or os.cpu_count() or 1)
    m = setup.measured
    row = Measured(DetectorConfigChoice(setup.precision, setup.threads, *(setup.hw or FULL_HW)), m.p50_ms,
                   m.p90_ms, m.cpu_ms, m.f1, m.recall, m.precision, min_ms=m.min_ms)  # fmt: skip
    plan = plan_cadence(row, n, fps, others)
    if replicas_set > 1:
        return replicas_by_hand(plan, row.cpu_ms, replicas_set), source
    replicated = replica_plan(plan, setup, doc) if replicas else None
    posed = starved_front_end(doc, odometry) if replicated is not None else None
    if posed is not None:  # measured better, but they would starve the front end: one detector, and why
        return replace(plan, layout_note=f"one detector: the last {odometry.split(':', 1)[0]} run here posed "
                       f"{posed:.0%} of its frames, replicas would starve its odometry"), source  # fmt: skip
    return (replicated or plan), source


def replicas_by_hand(plan: CadencePlan, cpu_ms: float, replicas: int) -> CadencePlan:
    """`plan`'s detector as `replicas` processes set by hand, taking turns (`CadencePlan.every_n`): together at most
    `replicas` times as often as one alone, and no more often than the cores the others leave allow.

    Why not the single detector's cadence: the replicas share the frames by rank, so a cadence planned for one
    (every 2nd frame) would leave each replica with a quarter of the frames and half the cores idle."""
    threads = plan.threads * replicas
    interval = max(plan.detect_alone_ms / replicas, cpu_ms / min(float(threads), plan.free_cores))
    return CadencePlan(plan.detect_alone_ms, interval, plan.free_cores, plan.others_cpu_ms, plan.fps, plan.threads,
                       replicas, f"{replicas} replicas set by hand (--detectors)")


def starved_front_end(doc: dict[str, Any] | None, odometry: str) -> float | None:
    """The share of its frames the odometry posed in the last real-time run with it here, where under
    `FRONT_END_KEEPS_UP`; None where it kept up (or no run recorded it). `setup_plan` starts no replicas then.

    Why the posed share and not the load alone (`replica_plan`'s bound): a front end that cannot keep up skips
    frames, so the CPU a run measures for it is what it got, not what it needs. On the AVX2 stand-in
    (benchmarks/avx2_stand_in.py) an `rgbd` run with one detector posed 283 of 1000 frames and measured 1.0 cores
    of others, under the +25 % bound, so the next runs started replicas, and the odometry posed 192-205."""
    posed = ((doc or {}).get("front_end_posed_share") or {}).get(odometry.split(":", 1)[0])
    return float(posed) if posed is not None and float(posed) < FRONT_END_KEEPS_UP else None


def replica_plan(plan: CadencePlan, setup: DetectorSetup, doc: dict[str, Any] | None) -> CadencePlan | None:
    """Single-thread replicas instead of `plan`'s one detector, where `measure_layouts` found them to detect more
    often beside the others' load on this machine. Only for the measured choice itself (explicit settings are
    kept), and only where the run's other services take no more than the load it was measured beside (+25 %):
    under a heavier front end (`rgbd`) flat-out replicas could starve it, and the single detector's cadence,
    held to its share, stays (and where the last run's front end was starved anyway, `setup_plan` keeps it:
    `starved_front_end`)."""
    if setup.origin != MEASURED_HERE or not doc or not doc.get("layouts") or not doc.get("choice"):
        return None
    choice = Measured.from_dict(doc["choice"]).config
    if (choice.precision, choice.hw, choice.threads) != (setup.precision, setup.hw or FULL_HW, setup.threads):
        return None
    layouts = [Layout(**d) for d in doc["layouts"]]
    best = best_layout(layouts)
    if best is None or best.replicas == 1:
        return None
    others_cores = plan.others_cpu_ms * plan.fps / 1e3
    if others_cores > 1.25 * best.load_cores + 0.05:
        return None
    single = next(lay for lay in layouts if lay.replicas == 1)
    note = (f"{best.label()} detected {best.detections_per_s:.1f}/s beside {best.load_cores:.2f} cores of load, "
            f"1 x {single.threads} threads {single.detections_per_s:.1f}/s (`semmap models doctor`)")
    return CadencePlan(plan.detect_alone_ms, 1e3 / best.detections_per_s, plan.free_cores, plan.others_cpu_ms,
                       plan.fps, best.threads, best.replicas, note)  # fmt: skip


def for_front_end(setup: DetectorSetup, odometry: str, model_dir: Path | None = None) -> DetectorSetup:
    """The measured choice again, for the front end this run really uses: `choose` with its CPU per frame (what
    a real-time run here measured, else the front end's own default estimate) instead of the doctor's `gt`
    estimate. A setup that is not the machine's measured choice (settings given) is kept, and so is the choice
    for a front end with neither figure (`file:`, an external SLAM).

    Why: the doctor plans for 30 ms of the other services a frame; ORB-SLAM3 and its checks take 45-50. fp32
    640x480 is then held to every 4th frame, where int8 at the same size, as faithful (F1 0.98), detects every 2nd
    frame for the same CPU (7-Scenes in real time: 12 landmarks of lockstep's 14 with fp32). And from the first
    run on: a machine that has not yet measured ORB-SLAM3 plans with its default estimate, not with `gt`'s."""
    if setup.origin != MEASURED_HERE:
        return setup
    doc = load_choice(model_dir)
    others, source = others_cpu_ms(odometry, doc)
    known = source.startswith("measured") or odometry.split(":", 1)[0] in DEFAULT_OTHERS_CPU_MS
    if doc is None or not known:
        return setup
    rows = [Measured.from_dict(r) for r in doc.get("rows", [])]
    cores = int((doc.get("key") or {}).get("cores") or os.cpu_count() or 1)
    best = choose(rows, cores, others=others)
    if best is None or (best.config.precision, best.config.threads, best.config.hw) == (
            setup.precision, setup.threads, setup.hw or FULL_HW):
        return setup
    c = best.config
    return DetectorSetup(c.precision, c.threads, (c.height, c.width),
                         f"{MEASURED_FOR_FRONT_END} ({odometry.split(':', 1)[0]}: {others:.0f} ms a frame, {source})",
                         best)


def load_detector_model(setup: DetectorSetup, model_dir: Path | None = None) -> Path | bytes:
    """The packaged model file of the setup's precision, or a copy resized in memory to its letterbox."""
    from semmap.runtime.models.model_store import packaged_model

    path = packaged_model(setup.precision)
    if setup.hw is None or setup.hw == FULL_HW:
        return path
    return model_bytes(setup.precision, setup.hw, model_dir)


def fidelity(measured: Measured) -> dict[str, Any]:
    """What a real-time run's detector keeps of lockstep's (fp32 at full size), as the doctor measured it on this
    machine's frames: for stats.json and the run's first and last lines (`describe_fidelity`).

    Why tell the user: real time on a CPU without VNNI detects at a smaller letterbox, so its map can lack small
    and far objects that lockstep maps (7-Scenes on the AVX2 stand-in: the far laptop, one half of the long table);
    the count alone would not say why."""
    return {"reference": f"fp32 {FULL_HW[1]}x{FULL_HW[0]}", "f1": round(measured.f1, 2),
            "f1_strict": round(measured.f1_strict, 2), "recall": round(measured.recall, 2),
            "recall_small": {c: round(r, 2) for c, r in measured.small_object_recall.items()}}  # fmt: skip


def describe_fidelity(d: dict[str, Any]) -> str | None:
    """One line from `fidelity`'s record; None where the detector is lockstep's own (nothing is lost)."""
    if min(d["f1"], d["recall"]) >= 0.995:
        return None
    small = format_recall(d["recall_small"])
    return (f"agrees with lockstep's ({d['reference']}) at F1 {d['f1']:.2f} ({d['f1_strict']:.2f} strictly) on "
            "this machine's frames"
            + (f"; recall {small}" if small else "")
            + ": small and far objects that a lockstep run maps may be missing")


def ordinal(n: int) -> str:  # "every 3rd frame"
    return {1: "every frame", 2: "every 2nd frame", 3: "every 3rd frame"}.get(n, f"every {n}th frame")


def describe_plan(plan: CadencePlan, source: str) -> str:
    """One line: what a real-time run will achieve with this plan."""
    if plan.replicas > 1:
        return (f"{plan.replicas} replicas of {plan.threads} thread{'s' if plan.threads > 1 else ''} taking turns, "
                f"{ordinal(plan.every_n)} at {plan.fps:.0f} fps ({plan.layout_note}; the other services take "
                f"{plan.others_cpu_ms:.0f} ms CPU per frame, {source}); expected {plan.detections_per_s:.1f} "
                "detections/s")
    return (f"detector {plan.detect_alone_ms:.0f} ms alone, ~{plan.interval_ms:.0f} ms in the run (the other services "
            f"take {plan.others_cpu_ms:.0f} ms CPU per frame, {source}: {plan.free_cores:.1f} cores left), "
            f"{ordinal(plan.every_n)} at {plan.fps:g} fps"
            + (f", taken as fast as it can (its {plan.threads} thread{'s' if plan.threads > 1 else ''} fit in the "
               "cores left)" if plan.flat_out else "")
            + f"; expected {plan.detections_per_s:.1f} detections/s"
            + (f" ({plan.layout_note})" if plan.layout_note else ""))
