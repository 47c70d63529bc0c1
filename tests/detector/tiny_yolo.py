"""A tiny YOLOv5-shaped checkpoint written in torch's zip format without torch, and a numpy reference forward.

Why: the converter must be tested on every machine (the real 15 MB `.pt` is only on machines that fetched it),
and its output must be checked against an independent implementation of the YOLOv5 modules (BN unfolded).
The pickle uses the same globals a real YOLOv5 checkpoint does (torch._utils._rebuild_tensor_v2,
models.common.Conv, ...), written by the pure-Python pickler with GLOBAL opcodes, so no fake torch modules
are ever imported.
"""

from __future__ import annotations

import collections
import io
import pickle
import zipfile
from typing import Any

import numpy as np

STRIDES = (8, 16, 32)
ANCHORS = np.array([[10, 13, 16, 30, 33, 23], [30, 61, 62, 45, 59, 119], [116, 90, 156, 198, 373, 326]], float)
_STORAGE = {np.dtype("float16"): "HalfStorage", np.dtype("float32"): "FloatStorage", np.dtype("int64"): "LongStorage"}


class Ref:
    """A global reference (module, name), pickled as a GLOBAL opcode."""

    def __init__(self, module: str, name: str) -> None:
        self.module, self.name = module, name

    def __call__(self) -> None:  # save_reduce insists on a callable
        raise NotImplementedError


class Mod:
    """A pickled torch module: class reference + state dict."""

    def __init__(self, qualname: str, state: dict[str, Any]) -> None:
        self.qualname, self.state = qualname, state


class Tensor:
    def __init__(self, arr: np.ndarray, dtype: str = "float16") -> None:
        self.arr = np.ascontiguousarray(arr, dtype=dtype)


class _Storage:
    def __init__(self, key: str, arr: np.ndarray) -> None:
        self.key, self.arr = key, arr


class _Pickler(pickle._Pickler):  # the pure-Python pickler lets us emit arbitrary GLOBALs
    dispatch = pickle._Pickler.dispatch.copy()

    def __init__(self, fh: io.BytesIO) -> None:
        super().__init__(fh, protocol=2)
        self.storages: list[_Storage] = []

    def persistent_id(self, obj: Any) -> Any:
        if isinstance(obj, _Storage):
            return ("storage", Ref("torch", _STORAGE[obj.arr.dtype]), obj.key, "cpu", int(obj.arr.size))
        return None

    def save_ref(self, obj: Ref) -> None:
        self.write(pickle.GLOBAL + f"{obj.module}\n{obj.name}\n".encode())
        self.memoize(obj)

    def save_mod(self, obj: Mod) -> None:
        module, name = obj.qualname.rsplit(".", 1)
        self.save_reduce(Ref(module, name), (), state=obj.state, obj=obj)

    def save_tensor(self, obj: Tensor) -> None:
        storage = _Storage(str(len(self.storages)), obj.arr.ravel())
        self.storages.append(storage)
        strides = tuple(s // obj.arr.itemsize for s in obj.arr.strides)
        args = (storage, 0, tuple(obj.arr.shape), strides, False, collections.OrderedDict())
        self.save_reduce(Ref("torch._utils", "_rebuild_tensor_v2"), args, obj=obj)

    dispatch[Ref] = save_ref
    dispatch[Mod] = save_mod
    dispatch[Tensor] = save_tensor


def torch_zip(obj: Any) -> bytes:
    """Serialise `obj` the way torch.save does: archive/data.pkl + archive/data/<key> + archive/version."""
    buf = io.BytesIO()
    p = _Pickler(buf)
    p.dump(obj)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as zf:
        zf.writestr("archive/data.pkl", buf.getvalue())
        for s in p.storages:
            zf.writestr(f"archive/data/{s.key}", s.arr.tobytes())
        zf.writestr("archive/version", "3\n")
    return out.getvalue()


def torch_zip_with_pickle(pkl: bytes) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        zf.writestr("archive/data.pkl", pkl)
        zf.writestr("archive/version", "3\n")
    return out.getvalue()


# ----------------------------------------------------------------------------------------------------------
# The tiny model


def _module(qualname: str, modules: dict[str, Mod] | None = None, params=None, buffers=None, **attrs) -> Mod:
    state = {
        "training": False,
        "_parameters": collections.OrderedDict(params or {}),
        "_buffers": collections.OrderedDict(buffers or {}),
        "_non_persistent_buffers_set": set(),
        "_modules": collections.OrderedDict(modules or {}),
        **attrs,
    }
    return Mod(qualname, state)


def _conv2d(rng, c1, c2, k, s, p, bias=False) -> Mod:
    w = rng.normal(0, 0.5 / np.sqrt(c1 * k * k), (c2, c1, k, k))
    b = Tensor(rng.normal(0, 0.5, c2), "float32") if bias else None
    return _module(
        "torch.nn.modules.conv.Conv2d", params={"weight": Tensor(w), "bias": b}, in_channels=c1,
        out_channels=c2, kernel_size=(k, k), stride=(s, s), padding=(p, p), dilation=(1, 1), transposed=False,
        output_padding=(0, 0), groups=1, padding_mode="zeros",
    )  # fmt: skip


def _bn(rng, c) -> Mod:
    return _module(
        "torch.nn.modules.batchnorm.BatchNorm2d",
        params={"weight": Tensor(rng.uniform(0.5, 1.5, c)), "bias": Tensor(rng.normal(0, 0.3, c))},
        buffers={
            "running_mean": Tensor(rng.normal(0, 0.3, c)),
            "running_var": Tensor(rng.uniform(0.5, 2.0, c)),
            "num_batches_tracked": Tensor(np.array(100), "int64"),
        },
        num_features=c, eps=0.001, momentum=0.03, affine=True, track_running_stats=True,
    )  # fmt: skip


def _conv(rng, c1, c2, k=1, s=1, p=None, **attrs) -> Mod:
    return _module(
        "models.common.Conv",
        {"conv": _conv2d(rng, c1, c2, k, s, k // 2 if p is None else p), "bn": _bn(rng, c2),
         "act": _module("torch.nn.modules.activation.SiLU", inplace=False)},
        **attrs,
    )  # fmt: skip


def _c3(rng, c1, c2, shortcut, **attrs) -> Mod:
    c_ = c2 // 2
    bott = _module(
        "models.common.Bottleneck", {"cv1": _conv(rng, c_, c_, 1), "cv2": _conv(rng, c_, c_, 3)}, add=shortcut
    )
    seq = _module("torch.nn.modules.container.Sequential", {"0": bott})
    return _module(
        "models.common.C3",
        {"cv1": _conv(rng, c1, c_), "cv2": _conv(rng, c1, c_), "cv3": _conv(rng, 2 * c_, c2), "m": seq},
        **attrs,
    )


def tiny_checkpoint(nc: int = 3, seed: int = 0, names: list[str] | None = None) -> bytes:
    """A YOLOv5-shaped model using every module type of yolov5s v6.0, with random weights, as `.pt` bytes."""
    return torch_zip(tiny_model(nc, seed, names))


def tiny_model(nc: int = 3, seed: int = 0, names: list[str] | None = None) -> dict[str, Any]:
    """The checkpoint's top-level dict (module tree of Mod records) before serialisation."""
    rng = np.random.default_rng(seed)
    no, na = nc + 5, 3
    pool = _module("torch.nn.modules.pooling.MaxPool2d", kernel_size=5, stride=1, padding=2, dilation=1,
                   return_indices=False, ceil_mode=False)  # fmt: skip
    layers = [
        _conv(rng, 3, 8, 6, 2, 2, f=-1, i=0),
        _conv(rng, 8, 16, 3, 2, f=-1, i=1),
        _c3(rng, 16, 16, True, f=-1, i=2),
        _conv(rng, 16, 16, 3, 2, f=-1, i=3),  # P3 /8
        _conv(rng, 16, 24, 3, 2, f=-1, i=4),  # P4 /16
        _conv(rng, 24, 32, 3, 2, f=-1, i=5),
        _module("models.common.SPPF", {"cv1": _conv(rng, 32, 16), "cv2": _conv(rng, 64, 32), "m": pool}, f=-1, i=6),
        _module(
            "torch.nn.modules.upsampling.Upsample",
            name="Upsample",
            size=None,
            scale_factor=2.0,
            mode="nearest",
            align_corners=None,
            f=-1,
            i=7,
        ),  # fmt: skip
        _module("models.common.Concat", d=1, f=[-1, 4], i=8),
        _c3(rng, 56, 24, False, f=-1, i=9),
    ]
    heads = {str(i): _conv2d(rng, c, na * no, 1, 1, 0, bias=True) for i, c in enumerate((16, 24, 32))}
    stride = np.array(STRIDES, dtype=np.float32)
    anchors = ANCHORS.reshape(3, 3, 2) / stride[:, None, None]
    layers.append(
        _module(
            "models.yolo.Detect",
            {"m": _module("torch.nn.modules.container.ModuleList", heads)},
            buffers={"anchors": Tensor(anchors, "float32")},
            nc=nc,
            no=no,
            nl=3,
            na=na,
            grid=[],
            inplace=True,
            f=[3, 9, 6],
            i=10,
            stride=Tensor(stride, "float32"),
        )  # fmt: skip
    )
    seq = _module("torch.nn.modules.container.Sequential", {str(i): m for i, m in enumerate(layers)})
    model = _module(
        "models.yolo.Model", {"model": seq}, yaml={"nc": nc}, names=names or [f"thing{i}" for i in range(nc)],
        stride=Tensor(stride, "float32"), nc=nc,
    )  # fmt: skip
    return {"epoch": -1, "best_fitness": None, "model": model, "ema": None, "optimizer": None}


# ----------------------------------------------------------------------------------------------------------
# Independent numpy forward (float64, BN not folded), following the YOLOv5 v6.0 module definitions


def _t(m: Mod, name: str) -> np.ndarray | None:
    for group in ("_parameters", "_buffers"):
        if name in m.state[group]:
            v = m.state[group][name]
            return None if v is None else v.arr.astype(np.float64)
    return None


def conv2d_ref(x: np.ndarray, w: np.ndarray, b: np.ndarray | None, stride: int, pad: int) -> np.ndarray:
    """x [C,H,W], w [O,C,k,k] -> [O,Ho,Wo]."""
    k = w.shape[2]
    xp = np.pad(x, ((0, 0), (pad, pad), (pad, pad)))
    cols = np.lib.stride_tricks.sliding_window_view(xp, (k, k), axis=(1, 2))[:, ::stride, ::stride]
    out = np.einsum("chwij,ocij->ohw", cols, w)
    return out if b is None else out + b[:, None, None]


def bn_ref(x, gamma, beta, mean, var, eps):
    return (x - mean[:, None, None]) / np.sqrt(var[:, None, None] + eps) * gamma[:, None, None] + beta[:, None, None]


def _silu(x):
    return x / (1 + np.exp(-x))


def _sigmoid(x):
    return 1 / (1 + np.exp(-x))


def _conv_mod(m: Mod, x):
    c = m.state["_modules"]["conv"]
    bn = m.state["_modules"]["bn"]
    y = conv2d_ref(x, _t(c, "weight"), None, c.state["stride"][0], c.state["padding"][0])
    y = bn_ref(y, _t(bn, "weight"), _t(bn, "bias"), _t(bn, "running_mean"), _t(bn, "running_var"), bn.state["eps"])
    return _silu(y)


def _maxpool(x, k=5):
    p = k // 2
    xp = np.pad(x, ((0, 0), (p, p), (p, p)), constant_values=-np.inf)
    return np.lib.stride_tricks.sliding_window_view(xp, (k, k), axis=(1, 2)).max(axis=(3, 4))


def _run(m: Mod, x):
    t, mods = m.qualname, m.state["_modules"]
    if t == "models.common.Conv":
        return _conv_mod(m, x)
    if t == "models.common.C3":
        a = _conv_mod(mods["cv1"], x)
        for b in mods["m"].state["_modules"].values():
            y = _conv_mod(b.state["_modules"]["cv2"], _conv_mod(b.state["_modules"]["cv1"], a))
            a = a + y if b.state["add"] else y
        return _conv_mod(mods["cv3"], np.concatenate([a, _conv_mod(mods["cv2"], x)]))
    if t == "models.common.SPPF":
        y = _conv_mod(mods["cv1"], x)
        y1 = _maxpool(y)
        y2 = _maxpool(y1)
        return _conv_mod(mods["cv2"], np.concatenate([y, y1, y2, _maxpool(y2)]))
    if t == "torch.nn.modules.upsampling.Upsample":
        return x.repeat(2, axis=1).repeat(2, axis=2)
    raise AssertionError(t)


def reference_forward(ckpt: dict[str, Any], image_chw: np.ndarray) -> np.ndarray:
    """The YOLOv5 inference output [N, no] for one [3,H,W] float image, straight from the module tree."""
    model = ckpt["model"]
    layers = list(model.state["_modules"]["model"].state["_modules"].values())
    outs: list[np.ndarray] = []
    x = image_chw.astype(np.float64)
    for idx, layer in enumerate(layers):
        f = layer.state["f"]
        srcs = [outs[idx + j] if j < 0 else outs[j] for j in ([f] if isinstance(f, int) else f)] if idx else [x]
        if layer.qualname == "models.common.Concat":
            outs.append(np.concatenate(srcs))
        elif layer.qualname == "models.yolo.Detect":
            return _detect_ref(layer, srcs)
        else:
            outs.append(_run(layer, srcs[0]))
    raise AssertionError("no Detect layer")


def _detect_ref(det: Mod, xs: list[np.ndarray]) -> np.ndarray:
    na, no = det.state["na"], det.state["no"]
    stride = det.state["stride"].arr.astype(np.float64)
    anchors = det.state["_buffers"]["anchors"].arr.astype(np.float64)
    z = []
    for i, x in enumerate(xs):
        conv = det.state["_modules"]["m"].state["_modules"][str(i)]
        y = conv2d_ref(x, _t(conv, "weight"), _t(conv, "bias"), 1, 0)
        ny, nx = y.shape[1:]
        y = _sigmoid(y.reshape(na, no, ny, nx).transpose(0, 2, 3, 1))  # (na, ny, nx, no)
        yv, xv = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
        grid = np.stack((xv, yv), 2)[None]  # (1, ny, nx, 2)
        anchor_grid = (anchors[i] * stride[i]).reshape(na, 1, 1, 2)
        xy = (y[..., 0:2] * 2 - 0.5 + grid) * stride[i]
        wh = (y[..., 2:4] * 2) ** 2 * anchor_grid
        z.append(np.concatenate([xy, wh, y[..., 4:]], -1).reshape(-1, no))
    return np.concatenate(z)
