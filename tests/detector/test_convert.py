"""The torch-free YOLOv5 converter: safety of the loader, numerical fidelity, determinism, real-model shapes."""

from __future__ import annotations

import io
import json
import os
import pickle
import zipfile

import numpy as np
import onnx
import onnxruntime as ort
import pytest

from semmap.runtime.models.yolov5_convert import (
    DECODE_SCOPE,
    CheckpointFormatError,
    UnsafeCheckpointError,
    build_onnx,
    convert_checkpoint,
    fold_batchnorm,
    load_checkpoint,
)

from .tiny_yolo import (
    Mod,
    Ref,
    Tensor,
    bn_ref,
    conv2d_ref,
    reference_forward,
    tiny_checkpoint,
    tiny_model,
    torch_zip,
    torch_zip_with_pickle,
)

IMGSZ = (64, 96)


def _session(model_bytes: bytes) -> ort.InferenceSession:
    return ort.InferenceSession(model_bytes, providers=["CPUExecutionProvider"])


@pytest.fixture(scope="module")
def tiny() -> tuple[bytes, bytes, list[str]]:
    pt = tiny_checkpoint(nc=3, seed=0)
    onnx_bytes, names = convert_checkpoint(pt, IMGSZ)
    return pt, onnx_bytes, names


# --- safety ------------------------------------------------------------------------------------------------


class _Evil:
    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_malicious_pickle_is_refused_without_running_code(tmp_path):
    marker = tmp_path / "pwned"
    pt = torch_zip_with_pickle(pickle.dumps({"model": _Evil(str(marker))}, protocol=2))
    with pytest.raises(UnsafeCheckpointError, match="system"):
        load_checkpoint(io.BytesIO(pt))
    assert not marker.exists()


@pytest.mark.parametrize(
    "ref",
    [Ref("builtins", "eval"), Ref("__builtin__", "exec"), Ref("subprocess", "Popen"), Ref("torch", "load")],
)
def test_unlisted_globals_are_refused(ref):
    pt = torch_zip({"model": Mod(f"{ref.module}.{ref.name}", {})})
    with pytest.raises(UnsafeCheckpointError, match="refusing"):
        load_checkpoint(io.BytesIO(pt))


def test_tensor_reaching_past_its_storage_is_refused():
    buf = torch_zip({"x": Tensor(np.zeros(4, np.float32), "float32")})
    # Rewrite the 4-element storage file as 2 elements: the declared size no longer fits.
    src = zipfile.ZipFile(io.BytesIO(buf))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        for name in src.namelist():
            data = src.read(name)
            zf.writestr(name, data[:8] if name == "archive/data/0" else data)
    with pytest.raises(UnsafeCheckpointError):
        load_checkpoint(io.BytesIO(out.getvalue()))


def test_not_a_checkpoint():
    with pytest.raises((CheckpointFormatError, zipfile.BadZipFile)):
        load_checkpoint(io.BytesIO(b"not a zip"))


# --- numerics ----------------------------------------------------------------------------------------------


def test_batchnorm_folding_equals_conv_then_bn():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(4, 11, 9))
    w = rng.normal(size=(6, 4, 3, 3)).astype(np.float32)
    bias = rng.normal(size=6).astype(np.float32)
    gamma, beta = rng.uniform(0.5, 2.0, 6), rng.normal(size=6)
    mean, var, eps = rng.normal(size=6), rng.uniform(0.1, 3.0, 6), 1e-3
    for b in (None, bias):
        ref = bn_ref(conv2d_ref(x, w.astype(np.float64), b, 1, 1), gamma, beta, mean, var, eps)
        wf, bf = fold_batchnorm(w, b, gamma, beta, mean, var, eps)
        assert wf.dtype == np.float32 and bf.dtype == np.float32
        np.testing.assert_allclose(conv2d_ref(x, wf.astype(np.float64), bf.astype(np.float64), 1, 1), ref,
                                   rtol=1e-5, atol=1e-5)  # fmt: skip


def test_converted_model_matches_numpy_reference(tiny):
    _, onnx_bytes, _ = tiny
    x = np.random.default_rng(1).random((1, 3, *IMGSZ), dtype=np.float32)
    out = _session(onnx_bytes).run(None, {"images": x})[0]
    n = 3 * sum((IMGSZ[0] // s) * (IMGSZ[1] // s) for s in (8, 16, 32))
    assert out.shape == (1, n, 8)
    ref = reference_forward(tiny_model(nc=3, seed=0), x[0].astype(np.float64))
    np.testing.assert_allclose(out[0, :, :4], ref[:, :4], rtol=1e-4, atol=2e-4)  # box, input pixels
    np.testing.assert_allclose(out[0, :, 4:], ref[:, 4:], rtol=1e-4, atol=1e-6)  # objectness, class probs


def test_graph_shapes_metadata_and_decode_scope(tiny):
    _, onnx_bytes, names = tiny
    model = onnx.load_from_string(onnx_bytes)
    onnx.checker.check_model(model)
    dims = [d.dim_value for d in model.graph.input[0].type.tensor_type.shape.dim]
    assert dims == [1, 3, *IMGSZ]
    meta = {p.key: p.value for p in model.metadata_props}
    assert json.loads(meta["names"]) == names == ["thing0", "thing1", "thing2"]
    assert json.loads(meta["stride"]) == [8, 16, 32]
    assert json.loads(meta["imgsz"]) == list(IMGSZ)
    assert not any(n.op_type == "BatchNormalization" for n in model.graph.node)  # folded
    assert any(n.name.startswith(DECODE_SCOPE) for n in model.graph.node)


def test_conversion_is_byte_deterministic(tiny):
    pt, onnx_bytes, _ = tiny
    again, _ = convert_checkpoint(pt, IMGSZ)
    assert again == onnx_bytes
    x = np.random.default_rng(2).random((1, 3, *IMGSZ), dtype=np.float32)
    s = _session(onnx_bytes)
    assert s.run(None, {"images": x})[0].tobytes() == s.run(None, {"images": x})[0].tobytes()


def test_input_size_must_be_multiple_of_32():
    with pytest.raises(ValueError, match="multiples of 32"):
        build_onnx(load_checkpoint(io.BytesIO(tiny_checkpoint())), (60, 96))


def test_unsupported_configuration_is_a_clear_error():
    ckpt = tiny_model()
    layers = ckpt["model"].state["_modules"]["model"].state["_modules"]
    layers["7"].state["mode"] = "bilinear"
    with pytest.raises(CheckpointFormatError, match="nearest"):
        build_onnx(load_checkpoint(io.BytesIO(torch_zip(ckpt))), IMGSZ)


# --- the real model ----------------------------------------------------------------------------------------


@pytest.mark.needs_model
def test_real_model_io_and_names(model_path):
    model = onnx.load(str(model_path))
    dims = [d.dim_value for d in model.graph.input[0].type.tensor_type.shape.dim]
    assert dims == [1, 3, 480, 640]
    out_dims = [d.dim_value for d in model.graph.output[0].type.tensor_type.shape.dim]
    assert out_dims == [1, 3 * (60 * 80 + 30 * 40 + 15 * 20), 85]
    names = json.loads({p.key: p.value for p in model.metadata_props}["names"])
    assert len(names) == 80 and names[0] == "person" and names[41] == "cup" and names[56] == "chair"


@pytest.mark.needs_model
def test_real_model_inference_is_deterministic(model_path):
    so = ort.SessionOptions()
    so.intra_op_num_threads = 2
    s = ort.InferenceSession(str(model_path), so, providers=["CPUExecutionProvider"])
    x = np.random.default_rng(0).random((1, 3, 480, 640), dtype=np.float32)
    a, b = s.run(None, {"images": x})[0], s.run(None, {"images": x})[0]
    assert a.shape == (1, 18900, 85)
    assert a.tobytes() == b.tobytes()
    assert a[..., 4:].min() >= 0.0 and a[..., 4:].max() <= 1.0  # sigmoid applied
