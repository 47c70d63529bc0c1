"""Does the int8 detector find what the fp32 one finds? Agreement per dataset, for a choice of calibration frames.

    .venv/bin/python benchmarks/bench_int8_agreement.py [--frames 30] [--calib synthetic|7scenes|both]

The int8 copy (`semmap models quantize`) is calibrated on frames; which frames every installation has decides
whether int8 can be a default. This makes int8 copies calibrated on the built-in synthetic scene (every
installation has it) and/or on 7-Scenes (only where ../shared/data is), runs fp32 and each copy on evenly spread
frames of 7-Scenes redkitchen, the Bonn crowd window and the KITTI 06 frames, and prints per dataset:
fp32 detections, int8 detections, matches (same class, IoU >= 0.5), recall (matched / fp32), precision
(matched / int8) and F1. Datasets missing from ../shared/data are skipped with a note.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from semmap.algorithms.detector.onnx_detector import DetectedBox, OnnxDetector  # noqa: E402
from semmap.datasets import find_data_root  # noqa: E402
from semmap.runtime.models.model_store import (  # noqa: E402
    default_model_path,
    quantize_int8,
    require_model,
    synthetic_calibration_images,
)

IOU_MATCH = 0.5
CALIB_FRAMES = 32


def iou(a: DetectedBox, b: DetectedBox) -> float:
    w = max(0.0, min(a.x2, b.x2) - max(a.x1, b.x1))
    h = max(0.0, min(a.y2, b.y2) - max(a.y1, b.y1))
    inter = w * h
    union = (a.x2 - a.x1) * (a.y2 - a.y1) + (b.x2 - b.x1) * (b.y2 - b.y1) - inter
    return inter / union if union > 0 else 0.0


def matches(ref: list[DetectedBox], other: list[DetectedBox]) -> int:
    """Greedy one-to-one matches of the same class with IoU >= IOU_MATCH, best pairs first."""
    pairs = sorted(
        ((iou(a, b), i, j) for i, a in enumerate(ref) for j, b in enumerate(other) if a.class_name == b.class_name),
        reverse=True,
    )
    used_a, used_b, n = set(), set(), 0
    for value, i, j in pairs:
        if value < IOU_MATCH:
            break
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            n += 1
    return n


def spread(items: list, n: int) -> list:
    if len(items) <= n:
        return items
    return [items[int(i)] for i in np.linspace(0, len(items) - 1, n)]


def test_sets(root: Path | None, frames: int) -> dict[str, list[Path]]:
    sets: dict[str, list[Path]] = {}
    if root is None:
        return sets
    seven = root / "7scenes-redkitchen"
    if seven.is_dir():
        sets["7-Scenes redkitchen"] = spread(sorted(seven.glob("frame-*.color.*")), frames)
    bonn = root / "bonn_crowd" / "rgb"
    if bonn.is_dir():
        sets["Bonn crowd"] = spread(sorted([*bonn.glob("*.png"), *bonn.glob("*.jpg")]), frames)
    kitti = root / "images" / "kitti06"
    if kitti.is_dir():
        sets["KITTI 06"] = sorted(p for p in kitti.glob("*.png"))
    return sets


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=30, help="frames per dataset, evenly spread")
    ap.add_argument("--calib", choices=("synthetic", "7scenes", "both"), default="both")
    args = ap.parse_args()
    fp32 = require_model(default_model_path())
    root = find_data_root()
    sets = test_sets(root, args.frames)
    if not sets:
        print("skipped: no datasets in ../shared/data or $SEMMAP_DATA", file=sys.stderr)
        return 0
    tmp = Path(tempfile.mkdtemp(prefix="semmap-int8-"))
    models: dict[str, Path] = {}
    if args.calib in ("synthetic", "both"):
        synthetic = synthetic_calibration_images(tmp / "synthetic", CALIB_FRAMES)
        models["int8, synthetic calibration"] = quantize_int8(fp32, synthetic, tmp / "syn.onnx")
    if args.calib in ("7scenes", "both") and "7-Scenes redkitchen" in sets:
        seven = spread(sorted((root / "7scenes-redkitchen").glob("frame-*.color.*")), CALIB_FRAMES)
        models["int8, 7-Scenes calibration"] = quantize_int8(fp32, seven, tmp / "seven.onnx")
    detectors = {"fp32": OnnxDetector(fp32, conf=0.4, iou=0.45, threads=2)}
    detectors.update({name: OnnxDetector(path, conf=0.4, iou=0.45, threads=2) for name, path in models.items()})
    print("| dataset (frames) | model | detections | matched to fp32 | recall | precision | F1 |")
    print("|---|---|---|---|---|---|---|")
    for dataset, paths in sets.items():
        images = [cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB) for p in paths]
        ref = [detectors["fp32"].detect(img) for img in images]
        n_ref = sum(len(r) for r in ref)
        print(f"| {dataset} ({len(images)}) | fp32 | {n_ref} | - | - | - | - |")
        for name in models:
            out = [detectors[name].detect(img) for img in images]
            n_out = sum(len(o) for o in out)
            m = sum(matches(r, o) for r, o in zip(ref, out, strict=True))
            recall, precision = m / max(n_ref, 1), m / max(n_out, 1)
            f1 = 2 * recall * precision / max(recall + precision, 1e-9)
            print(f"| {dataset} ({len(images)}) | {name} | {n_out} | {m} | {recall:.2f} | {precision:.2f} | {f1:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
