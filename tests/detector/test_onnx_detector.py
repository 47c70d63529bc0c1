"""OnnxDetector: geometry, NMS, names, both output layouts, depth gate, and real detections on real frames."""

from __future__ import annotations

import json

import cv2
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from semmap.algorithms.detector.onnx_detector import (
    DetectedBox,
    OnnxDetector,
    choose_providers,
    depth_gate,
    letterbox,
    load_names_file,
    nms,
    parse_names,
    unletterbox,
    xywh_to_xyxy,
)
from semmap.datasets.images import read_depth_u16, read_rgb
from semmap.runtime.models.detector_choice import detections_down_to

# --- synthetic models --------------------------------------------------------------------------------------


def _const_model(path, out: np.ndarray, input_shape=(1, 3, 64, 64), names: str | None = None) -> str:
    """A model whose output is `out` whatever the image (it still reads the input, so ORT keeps it)."""
    mean = helper.make_node("ReduceMean", ["images"], ["m"], keepdims=0)
    zero = helper.make_node("Mul", ["m", "zero"], ["z"])
    add = helper.make_node("Add", ["const", "z"], ["output0"])
    graph = helper.make_graph(
        [mean, zero, add],
        "const",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, list(input_shape))],
        [helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(out.shape))],
        initializer=[
            numpy_helper.from_array(out.astype(np.float32), "const"),
            numpy_helper.from_array(np.array(0.0, np.float32), "zero"),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    if names is not None:
        helper.set_model_props(model, {"names": names})
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return str(path)


# Candidates in 64x64 model-input pixels: (cx, cy, w, h, class, score)
CANDIDATES = [
    (32.0, 32.0, 20.0, 10.0, 2, 0.9),  # A: car, kept
    (33.0, 32.0, 20.0, 10.0, 2, 0.8),  # B: car overlapping A: suppressed
    (33.0, 32.0, 20.0, 10.0, 1, 0.7),  # C: bicycle on top of A: kept (class-wise NMS)
    (10.0, 20.0, 4.0, 4.0, 0, 0.3),  # D: below the confidence threshold
]
ULTRA_NAMES = "{0: 'person', 1: 'bicycle', 2: 'car'}"


N_OUT = 50  # candidates in the synthetic outputs: the four above, then empty ones


def _yolov8_output(n: int = N_OUT) -> np.ndarray:
    out = np.zeros((1, 4 + 3, n), np.float32)
    for j, (cx, cy, w, h, c, s) in enumerate(CANDIDATES):
        out[0, :4, j] = (cx, cy, w, h)
        out[0, 4 + c, j] = s
    return out


def _yolov5_output(n: int = N_OUT) -> np.ndarray:
    out = np.zeros((1, n, 5 + 3), np.float32)
    for j, (cx, cy, w, h, c, s) in enumerate(CANDIDATES):
        out[0, j, :5] = (cx, cy, w, h, 1.0)
        out[0, j, 5 + c] = s
    return out


@pytest.fixture
def v8_model(tmp_path):
    return _const_model(tmp_path / "v8.onnx", _yolov8_output(), names=ULTRA_NAMES)


@pytest.fixture
def v5_model(tmp_path):
    return _const_model(tmp_path / "v5.onnx", _yolov5_output(), names=json.dumps(["person", "bicycle", "car"]))


# An image of 128x96 (w x h) letterboxes into 64x64 at scale 0.5 with 8 px grey above and below.
IMAGE = np.full((96, 128, 3), 30, np.uint8)


def _orig(cx, cy, w, h):
    return ((cx - w / 2) / 0.5, (cy - h / 2 - 8) / 0.5, (cx + w / 2) / 0.5, (cy + h / 2 - 8) / 0.5)


@pytest.mark.parametrize("fixture,layout", [("v8_model", "yolov8"), ("v5_model", "yolov5")])
def test_both_layouts_decode_nms_and_unletterbox(request, fixture, layout):
    det = OnnxDetector(request.getfixturevalue(fixture), conf=0.4, threads=1)
    assert det.layout == layout
    assert det.names == ["person", "bicycle", "car"]
    boxes = det.detect(IMAGE)
    assert [(b.class_name, b.class_id) for b in boxes] == [("car", 2), ("bicycle", 1)]
    assert boxes[0].score == pytest.approx(0.9, abs=1e-6) and boxes[1].score == pytest.approx(0.7, abs=1e-6)
    np.testing.assert_allclose([boxes[0].x1, boxes[0].y1, boxes[0].x2, boxes[0].y2], _orig(*CANDIDATES[0][:4]))
    np.testing.assert_allclose([boxes[1].x1, boxes[1].y1, boxes[1].x2, boxes[1].y2], _orig(*CANDIDATES[2][:4]))


def test_objectness_multiplies_class_probability(tmp_path):
    out = _yolov5_output()
    out[0, :, 4] = 0.5  # halves every score: only A (0.45) stays above 0.4
    det = OnnxDetector(_const_model(tmp_path / "m.onnx", out, names='["person","bicycle","car"]'), threads=1)
    boxes = det.detect(IMAGE)
    assert [b.class_name for b in boxes] == ["car"]
    assert boxes[0].score == pytest.approx(0.45, abs=1e-6)


@pytest.mark.parametrize("fixture", ["v8_model", "v5_model"])
def test_a_class_of_its_own_threshold_keeps_what_the_common_one_drops(request, fixture):
    """D, a person at 0.3, is under the common 0.4; with person's own 0.25 it is kept (the dynamic mask's people,
    where a missed one costs more than a false one); the other classes keep 0.4 (the bicycle at 0.7 stays, a car
    at 0.8 stays suppressed). A name the model does not have is reported, not used."""
    det = OnnxDetector(request.getfixturevalue(fixture), conf=0.4, threads=1, class_confidence={"person": 0.25})
    boxes = det.detect(IMAGE)
    assert [(b.class_name, round(b.score, 3)) for b in boxes] == [("car", 0.9), ("bicycle", 0.7), ("person", 0.3)]
    np.testing.assert_allclose([boxes[2].x1, boxes[2].y1, boxes[2].x2, boxes[2].y2], _orig(*CANDIDATES[3][:4]))
    stricter = OnnxDetector(request.getfixturevalue(fixture), conf=0.4, threads=1, class_confidence={"car": 0.95})
    assert [b.class_name for b in stricter.detect(IMAGE)] == ["bicycle"]
    typo = OnnxDetector(request.getfixturevalue(fixture), threads=1, class_confidence={"pedestrian": 0.2})
    assert typo.unknown_confidence_classes == ["pedestrian"]  # (the detector service logs them at start)
    assert [b.class_name for b in typo.detect(IMAGE)] == ["car", "bicycle"]


def test_a_threshold_lowered_after_construction_reaches_the_decode(v5_model):
    """`semmap models doctor` lowers `conf` on a built detector to see the boxes just under the threshold (a tie,
    not a disagreement). The per-class thresholds are derived from `conf`; when a change did not reach them, the
    doctor read every tie as a disagreement and on an AVX2-only CPU no smaller letterbox agreed any more."""
    det = OnnxDetector(v5_model, conf=0.4, threads=1)
    assert [b.class_name for b in det.detect(IMAGE)] == ["car", "bicycle"]
    det.conf = 0.25
    assert [(b.class_name, round(b.score, 3)) for b in det.detect(IMAGE)] == [("car", 0.9), ("bicycle", 0.7),
                                                                              ("person", 0.3)]  # fmt: skip
    assert [[b.class_name for b in boxes] for boxes in detections_down_to(det, [IMAGE], 0.25)] == [
        ["car", "bicycle", "person"]
    ]
    det.conf = 0.4
    assert det.conf == 0.4 and [b.class_name for b in det.detect(IMAGE)] == ["car", "bicycle"]
    own = OnnxDetector(v5_model, conf=0.4, threads=1, class_confidence={"car": 0.95})
    assert [[b.class_name for b in boxes] for boxes in detections_down_to(own, [IMAGE], 0.25)] == [
        ["bicycle", "person"]
    ]  # a class of its own threshold keeps it
    assert own.conf == 0.4 and [b.class_name for b in own.detect(IMAGE)] == ["bicycle"]


def test_allow_and_deny_lists(v8_model):
    assert [b.class_name for b in OnnxDetector(v8_model, allow={"car"}, threads=1).detect(IMAGE)] == ["car"]
    assert [b.class_name for b in OnnxDetector(v8_model, deny={"car"}, threads=1).detect(IMAGE)] == ["bicycle"]
    with pytest.raises(ValueError, match="does not know"):
        OnnxDetector(v8_model, allow={"cat"}, threads=1)


def test_names_from_file_and_mismatch(v8_model, tmp_path):
    txt = tmp_path / "names.txt"
    txt.write_text("a\nb\n\nc\n")
    assert OnnxDetector(v8_model, names=txt, threads=1).names == ["a", "b", "c"]
    assert OnnxDetector(v8_model, names=["x", "y", "z"], threads=1).names == ["x", "y", "z"]
    with pytest.raises(ValueError, match="3 classes but 2 names"):
        OnnxDetector(v8_model, names=["x", "y"], threads=1)


def test_names_decide_the_layout_when_shapes_are_ambiguous(tmp_path):
    # 4 candidates < 7 channels: only the class count tells which axis holds the channels
    det = OnnxDetector(_const_model(tmp_path / "m.onnx", _yolov8_output(4), names=ULTRA_NAMES), threads=1)
    assert det.layout == "yolov8"
    assert [b.class_name for b in det.detect(IMAGE)] == ["car", "bicycle"]


def test_no_names_anywhere_gives_placeholders(tmp_path):
    det = OnnxDetector(_const_model(tmp_path / "m.onnx", _yolov8_output()), threads=1)
    assert det.names == ["class0", "class1", "class2"]


@pytest.mark.parametrize("shape", [(1, 10), (1, 3, 4), (1, 2, 3, 4)])
def test_unsupported_output_layout_is_a_value_error(tmp_path, shape):
    with pytest.raises(ValueError, match="unsupported output"):
        OnnxDetector(_const_model(tmp_path / "bad.onnx", np.zeros(shape, np.float32)), threads=1)


def test_dynamic_input_letterboxes_to_a_rectangle(tmp_path):
    det = OnnxDetector(_const_model(tmp_path / "d.onnx", _yolov8_output(), (1, 3, "h", "w")), threads=1)
    assert det.input_hw is None
    assert det._target_hw(480, 640) == (480, 640)
    assert det._target_hw(370, 1226) == (224, 640)


def test_bad_image_is_a_value_error(v8_model):
    det = OnnxDetector(v8_model, threads=1)
    with pytest.raises(ValueError, match="uint8"):
        det.detect(np.zeros((10, 10), np.uint8))


def test_provider_preference():
    assert choose_providers(["CPUExecutionProvider"]) == ["CPUExecutionProvider"]
    assert choose_providers(["CUDAExecutionProvider", "TensorrtExecutionProvider", "CPUExecutionProvider"]) == [
        "TensorrtExecutionProvider",
        "CUDAExecutionProvider",
        "CPUExecutionProvider",
    ]


# --- names -------------------------------------------------------------------------------------------------


def test_parse_names_forms(tmp_path):
    assert parse_names('["a", "b"]') == ["a", "b"]
    assert parse_names('{"0": "a", "1": "b"}') == ["a", "b"]
    assert parse_names("{0: 'person', 1: 'bicycle', 2: 'dining table'}") == ["person", "bicycle", "dining table"]
    for bad in ("{1: 'a'}", "[1, 2]", "not names", "__import__('os')"):
        with pytest.raises(ValueError):
            parse_names(bad)
    (tmp_path / "n.json").write_text('["x", "y"]')
    assert load_names_file(tmp_path / "n.json") == ["x", "y"]


# --- geometry ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("hw", [(480, 640), (370, 1226), (500, 300), (100, 100)])
def test_letterbox_round_trip(hw):
    h, w = hw
    img = np.zeros((h, w, 3), np.uint8)
    box = np.array([[0.2 * w, 0.3 * h, 0.7 * w, 0.9 * h]])
    x1, y1, x2, y2 = box[0].round().astype(int)
    img[y1:y2, x1:x2] = 255
    out, r, (px, py) = letterbox(img, (480, 640))
    assert out.shape == (480, 640, 3)
    assert r == pytest.approx(min(480 / h, 640 / w))
    if py:
        assert (out[: py - 1] == 114).all()
    if px:
        assert (out[:, : px - 1] == 114).all()
    in_model = box * r + np.array([px, py, px, py])
    back = unletterbox(in_model, r, (px, py), (h, w))
    np.testing.assert_allclose(back, box, atol=1e-9)
    # the white rectangle lands where the transformed box says (to a pixel)
    mx1, my1, mx2, my2 = in_model[0]
    white = np.argwhere(out[..., 0] > 127)  # edges are interpolated
    assert abs(white[:, 1].min() - mx1) <= 1.5 and abs(white[:, 1].max() + 1 - mx2) <= 1.5
    assert abs(white[:, 0].min() - my1) <= 1.5 and abs(white[:, 0].max() + 1 - my2) <= 1.5


def test_unletterbox_clips_to_image():
    back = unletterbox(np.array([[-50.0, -50.0, 700.0, 500.0]]), 1.0, (0, 0), (480, 640))
    np.testing.assert_allclose(back, [[0, 0, 640, 480]])


# --- NMS ---------------------------------------------------------------------------------------------------


def test_nms_basic_and_classwise():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [20, 20, 30, 30], [0, 0, 10, 10]], float)
    scores = np.array([0.9, 0.8, 0.7, 0.95])
    assert nms(boxes, scores, 0.45).tolist() == [3, 2]
    assert nms(boxes, scores, 0.45, np.array([0, 0, 0, 1])).tolist() == [3, 0, 2]
    assert nms(np.zeros((0, 4)), np.zeros(0)).size == 0


def test_nms_agrees_with_opencv_on_random_boxes():
    rng = np.random.default_rng(7)
    xy = rng.uniform(0, 200, (300, 2))
    wh = rng.uniform(5, 80, (300, 2))
    boxes = np.concatenate([xy, xy + wh], 1)
    scores = rng.uniform(0.4, 1.0, 300)
    classes = rng.integers(0, 4, 300)
    ours = nms(boxes, scores, 0.45, classes)
    ref = cv2.dnn.NMSBoxesBatched(
        [list(map(float, np.r_[b[:2], b[2:] - b[:2]])) for b in boxes], scores.tolist(), classes.tolist(), 0.0, 0.45
    )
    assert sorted(ours.tolist()) == sorted(np.asarray(ref).ravel().tolist())


def test_xywh_to_xyxy():
    np.testing.assert_allclose(xywh_to_xyxy(np.array([[10.0, 20.0, 4.0, 6.0]])), [[8, 17, 12, 23]])


# --- depth gate --------------------------------------------------------------------------------------------


def _box(x1, y1, x2, y2):
    return DetectedBox(x1, y1, x2, y2, 0, "thing", 0.9)


def test_depth_gate_median_of_central_half():
    depth = np.full((100, 100), 5000, np.uint16)  # background at 5 m (mm units)
    depth[30:70, 30:70] = 1000  # object at 1 m, filling the central half of the box below
    depth[35:40, 35:40] = 0  # some invalid pixels
    kept = depth_gate([_box(20, 20, 80, 80)], depth, 0.001)
    assert len(kept) == 1 and kept[0][1] == pytest.approx(1.0)


def test_depth_gate_drops_out_of_range_and_empty():
    depth = np.zeros((100, 100), np.uint16)
    depth[:, :50] = 100  # 0.1 m: too near
    depth[:, 50:] = 30000  # 30 m: too far
    assert depth_gate([_box(0, 0, 40, 40), _box(60, 0, 100, 40)], depth, 0.001) == []
    depth[:] = 0
    assert depth_gate([_box(10, 10, 40, 40)], depth, 0.001) == []
    depth[:] = 2000
    kept = depth_gate([_box(10, 10, 40, 40), _box(0.2, 0.2, 0.8, 0.8)], depth, 0.001, min_m=0.2, max_m=25.0)
    assert [d for _, d in kept] == [2.0, 2.0]  # even a sub-pixel box reads one pixel


# --- real frames -------------------------------------------------------------------------------------------

# What the fp32 model finds at conf 0.4 on these frames (measured): cups and chairs in all four.
SEVEN_SCENES_FRAMES = {
    0: {"cup", "chair"},  # + dining table
    250: {"cup", "chair"},  # + tv, book
    500: {"cup", "chair"},  # + tv, book
    750: {"cup", "chair"},  # + laptop, mouse
}


@pytest.mark.needs_model
@pytest.mark.needs_data
@pytest.mark.parametrize("frame", sorted(SEVEN_SCENES_FRAMES))
def test_real_7scenes_detections(yolo, kitchen_dir, frame):
    rgb = read_rgb(kitchen_dir / f"frame-{frame:06d}.color.jpg")
    boxes = yolo.detect(rgb)
    found = {b.class_name for b in boxes}
    assert SEVEN_SCENES_FRAMES[frame] <= found, found
    assert all(0 <= b.x1 < b.x2 <= 640 and 0 <= b.y1 < b.y2 <= 480 and b.score >= 0.4 for b in boxes)
    assert [b.score for b in boxes] == sorted((b.score for b in boxes), reverse=True)
    assert yolo.detect(rgb) == boxes  # deterministic


@pytest.mark.needs_model
@pytest.mark.needs_data
def test_real_kitti_cars(yolo, data_root):
    path = data_root / "images" / "kitti06" / "kitti06-12-color.png"
    if not path.is_file():
        pytest.skip(f"{path} absent")
    rgb = read_rgb(path)
    assert rgb.shape == (370, 1226, 3)
    cars = [b for b in yolo.detect(rgb) if b.class_name == "car"]
    assert len(cars) >= 2
    assert all(0 <= b.x1 < b.x2 <= 1226 and 0 <= b.y1 < b.y2 <= 370 for b in cars)


@pytest.mark.needs_model
@pytest.mark.needs_data
def test_real_depth_gate_on_cup(yolo, kitchen_dir):
    scene = kitchen_dir
    boxes = yolo.detect(read_rgb(scene / "frame-000000.color.jpg"))
    depth = read_depth_u16(scene / "frame-000000.depth.png")
    assert depth.dtype == np.uint16
    kept = dict((b.class_name, d) for b, d in depth_gate(boxes, depth, 0.001))
    assert 0.3 < kept["cup"] < 3.0  # a mug on the table, seen from standing height


def _skip_without_vnni() -> None:
    """int8 detections are checked where int8 can be chosen: a CPU with VNNI (or ARM dot products). Without them
    onnxruntime's 8-bit kernels saturate (AVX2-only EPYC: the cup of frame 750 is lost, F1 0.84-0.88 against fp32), and
    `detector.precision: auto` does not take int8 there (semmap.runtime.models.detector_choice, `semmap models
    doctor`)."""
    from semmap.runtime.models.detector_choice import hardware_key, has_vnni

    if not has_vnni(hardware_key()):
        pytest.skip("this CPU has no VNNI: int8 is not chosen here (semmap models doctor), its agreement not required")


@pytest.mark.needs_model
@pytest.mark.needs_data
def test_int8_copy_keeps_detections(model_path, kitchen_dir, tmp_path):
    from semmap.runtime.models.model_store import quantize_int8

    _skip_without_vnni()
    scene = kitchen_dir
    calib = [scene / f"frame-{i:06d}.color.jpg" for i in (100, 300, 450, 600, 850, 950)]
    q = quantize_int8(model_path, calib, tmp_path / "int8.onnx")
    assert q.stat().st_size < model_path.stat().st_size / 3
    det = OnnxDetector(q, threads=2)
    assert len(det.names) == 80
    for frame in (0, 750):
        found = {b.class_name for b in det.detect(read_rgb(scene / f"frame-{frame:06d}.color.jpg"))}
        assert {"cup", "chair"} <= found, (frame, found)


@pytest.mark.needs_model
@pytest.mark.needs_data
def test_int8_copy_calibrated_on_the_synthetic_scene(model_path, kitchen_dir, tmp_path):
    """An installation without any dataset still gets an int8 copy (`./dev.sh setup` falls back to this), and it
    finds the kitchen's objects as the fp32 model does."""
    import subprocess
    import sys

    out = tmp_path / "int8.onnx"
    cmd = [sys.executable, "-m", "semmap.cli", "models", "quantize", "--model", str(model_path), "--out", str(out)]
    refused = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert refused.returncode == 2 and "--synthetic" in refused.stderr
    made = subprocess.run([*cmd, "--synthetic", "--max-images", "8"], capture_output=True, text=True, timeout=300)
    assert made.returncode == 0, made.stderr
    assert made.stdout.strip() == str(out) and "calibrating on 8 images" in made.stderr
    _skip_without_vnni()  # (the copy is made everywhere; whether it finds what fp32 finds depends on the CPU)
    det = OnnxDetector(out, threads=2)
    for frame in (0, 750):
        found = {b.class_name for b in det.detect(read_rgb(kitchen_dir / f"frame-{frame:06d}.color.jpg"))}
        assert {"cup", "chair"} <= found, (frame, found)


def _int8_weights(path) -> np.ndarray:
    """Every 8-bit weight of a QDQ model (its int8 initializers), flattened."""
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(path))
    return np.concatenate([numpy_helper.to_array(t).ravel() for t in model.graph.initializer
                           if t.data_type == onnx.TensorProto.INT8])  # fmt: skip


@pytest.mark.needs_model
@pytest.mark.needs_data
def test_int8w7_copy_agrees_with_fp32_on_any_cpu(model_path, kitchen_dir, tmp_path):
    """The 7-bit-weight copy (`semmap models quantize --weight-bits 7`, precision int8w7) keeps its weights in
    [-64, 64], so that a CPU without VNNI, which sums pairs of 8-bit products in 16 bits, cannot saturate
    (255 x 64 x 2 = 32640 <= 32767; with 8-bit weights 255 x 127 x 2 > 32767). Unlike the 8-bit copy its detections are
    therefore checked on every CPU: where the 8-bit copy loses the cup of frame 750 (AVX2-only EPYC), this one
    must find it."""
    import subprocess
    import sys

    calib = [kitchen_dir / f"frame-{i:06d}.color.jpg" for i in (100, 300, 450, 600, 850, 950)]
    out = tmp_path / "int8w7.onnx"
    made = subprocess.run([sys.executable, "-m", "semmap.cli", "models", "quantize", *map(str, calib),
                           "--model", str(model_path), "--weight-bits", "7", "--out", str(out)],
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert made.returncode == 0, made.stderr
    w7 = _int8_weights(out)
    assert w7.min() >= -64 and w7.max() <= 64, (w7.min(), w7.max())
    assert max(-int(w7.min()), int(w7.max())) == 64  # (each channel's largest weight takes the full 7-bit range)
    det = OnnxDetector(out, threads=2)
    for frame in (0, 750):
        found = {b.class_name for b in det.detect(read_rgb(kitchen_dir / f"frame-{frame:06d}.color.jpg"))}
        assert {"cup", "chair"} <= found, (frame, found)
