"""The real-time detector choice: input resizing, the agreement rule, the cache keyed by the machine,
the frame budget and `semmap models doctor`. Nothing here times anything for pass/fail: the measured rows are
made up; only their bookkeeping is checked."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest

from semmap.algorithms.detector.onnx_detector import DetectedBox
from semmap.runtime.models import detector_choice as dc
from semmap.runtime.models.model_store import MODEL_FILENAME
from semmap.runtime.models.yolov5_convert import convert_checkpoint, resize_input

from .tiny_yolo import tiny_checkpoint


def _box(cls: str, x: float, score: float = 0.8, size: float = 20.0) -> DetectedBox:
    return DetectedBox(x, 10.0, x + size, 10.0 + size, 0, cls, score)


def _row(precision: str, threads: int, hw: tuple[int, int], p50: float, cpu: float, f1: float) -> dc.Measured:
    return dc.Measured(dc.DetectorConfigChoice(precision, threads, *hw), p50, p50 * 1.1, cpu, f1, f1, f1,
                       {"cup": f1}, f1, p50)  # fmt: skip


def _run(model: bytes, x: np.ndarray) -> np.ndarray:
    sess = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
    return sess.run(None, {"images": x})[0]


# --- resizing the input of a converted model --------------------------------------------------------------


def test_resized_model_equals_one_converted_at_that_size() -> None:
    pt = tiny_checkpoint(nc=3, seed=0)
    small, _ = convert_checkpoint(pt, (64, 96))
    big, _ = convert_checkpoint(pt, (96, 128))
    resized = resize_input(onnx.load_from_string(small), (96, 128))
    assert json.loads({p.key: p.value for p in resized.metadata_props}["imgsz"]) == [96, 128]
    x = np.random.default_rng(0).random((1, 3, 96, 128), dtype=np.float32)
    np.testing.assert_allclose(_run(resized.SerializeToString(), x), _run(big, x), rtol=1e-5, atol=1e-4)
    same = resize_input(onnx.load_from_string(small), (64, 96))  # a no-op round trip
    assert {t.name: t.raw_data for t in same.graph.initializer} == {
        t.name: t.raw_data for t in onnx.load_from_string(small).graph.initializer}


def test_resize_refuses_foreign_models_and_odd_sizes() -> None:
    small, _ = convert_checkpoint(tiny_checkpoint(nc=3, seed=0), (64, 96))
    with pytest.raises(ValueError, match="multiples of 32"):
        resize_input(onnx.load_from_string(small), (100, 96))
    foreign = onnx.load_from_string(small)
    del foreign.metadata_props[:]
    with pytest.raises(ValueError, match="converted by semmap"):
        resize_input(foreign, (96, 96))


# --- the agreement rule ------------------------------------------------------------------------------------


def test_agreement_counts_same_class_overlaps_and_recall_per_class() -> None:
    ref = [[_box("cup", 0), _box("book", 100)], [_box("chair", 0, size=100)]]
    out = [[_box("cup", 2), _box("cup", 100)], [_box("chair", 5, size=100), _box("tv", 300)]]
    f1, recall, precision, per_class = dc.agreement(ref, out)
    assert (recall, precision) == (2 / 3, 2 / 4)  # the book was called a cup; the tv is extra
    assert f1 == pytest.approx(2 * (2 / 3) * 0.5 / (2 / 3 + 0.5))
    assert per_class == {"book": 0.0, "chair": 1.0, "cup": 1.0}


def test_a_score_just_under_the_threshold_is_a_tie_not_a_miss() -> None:
    ref = [[_box("cup", 0, score=0.45), _box("book", 100, score=0.35)]]
    out = [[_box("cup", 1, score=0.37), _box("book", 101, score=0.42)]]
    strict = dc.agreement(ref, out, conf=0.4, margin=0.0)
    tolerant = dc.agreement(ref, out, conf=0.4, margin=dc.TIE_MARGIN)
    assert strict[0] == 0.0  # at the threshold alone the two disagree on both boxes
    assert tolerant[:3] == (1.0, 1.0, 1.0)
    far = dc.agreement(ref, [[_box("cup", 1, score=0.2)]], conf=0.4, margin=dc.TIE_MARGIN)
    assert far[1] == 0.0  # 0.2 is no tie with 0.45


def test_choice_is_the_quickest_in_a_run_among_those_that_agree() -> None:
    rows = [
        _row("fp32", 2, (480, 640), 110, 200, 1.0),
        _row("int8", 2, (480, 640), 105, 190, 0.85),  # faster, but disagrees
        _row("fp32", 2, (384, 512), 70, 130, 0.93),
        _row("fp32", 1, (384, 512), 95, 95, 0.93),  # slower alone, cheaper in a run sharing 2 cores
        _row("fp32", 2, (320, 416), 40, 75, 0.87),  # fastest, disagrees (small objects)
    ]
    best = dc.choose(rows, cores=2)
    assert best is not None and best.config == dc.DetectorConfigChoice("fp32", 1, 384, 512)
    assert dc.choose(rows, cores=8).config == dc.DetectorConfigChoice("fp32", 2, 384, 512)  # cores to spare
    assert dc.choose([rows[1], rows[4]], cores=2) is None


def test_where_the_full_frame_keeps_up_the_most_faithful_configuration_wins() -> None:
    """A VNNI EPYC's doctor: int8 640x480 agrees nearly fully (F1 0.99) and still detects every
    2nd frame of a run, so it beats the faster int8 512x384 (F1 0.92, which loses a far laptop and half a table);
    on the AVX2-only EPYC nothing at 640x480 keeps up, and the fastest agreeing one stays the choice."""
    vnni = [
        _row("fp32", 2, (480, 640), 81, 155, 1.0),  # faithful, but 10 a second
        _row("int8", 2, (480, 640), 39, 64, 0.99),
        _row("int8", 1, (480, 640), 53, 54, 0.99),
        _row("int8", 2, (384, 512), 28, 46, 0.92),  # the fastest that agrees
        _row("int8", 1, (384, 512), 35, 36, 0.92),
        _row("int8", 2, (320, 416), 19, 30, 0.87),  # disagrees
    ]
    assert dc.rank_for_realtime(vnni, 2)[0].config.hw == (384, 512)
    best = dc.choose(vnni, cores=2)
    assert best is not None and best.config == dc.DetectorConfigChoice("int8", 1, 480, 640)
    avx2 = [
        _row("fp32", 2, (480, 640), 75, 150, 1.0),
        _row("fp32", 1, (480, 640), 142, 142, 1.0),
        _row("fp32", 2, (384, 640), 60, 118, 0.90),
        _row("fp32", 2, (384, 512), 48, 97, 0.90),
        _row("fp32", 1, (384, 512), 92, 92, 0.90),
    ]
    best = dc.choose(avx2, cores=2)
    assert best is not None and best.config == dc.DetectorConfigChoice("fp32", 2, 384, 512)
    assert best == dc.rank_for_realtime(avx2, 2)[0]


def _chosen(rows: list[dc.Measured]) -> dc.DetectorConfigChoice:
    best = dc.choose(rows, cores=2)
    assert best is not None
    return best.config


def test_without_vnni_the_7bit_int8_copy_takes_over_where_it_agrees_and_is_cheaper() -> None:
    """The doctor on AVX2 kernels (stand-in): the 8-bit int8 copy disagrees at every size (its products
    saturate), the 7-bit one agrees where fp32 does and costs less CPU, so it is the choice; the same rule on a VNNI
    machine keeps the 8-bit copy, which is more faithful there at the same speed."""
    avx2 = [
        _row("fp32", 2, (480, 640), 103, 207, 1.0),
        _row("int8", 2, (480, 640), 86, 149, 0.88),  # disagrees
        _row("int8w7", 1, (480, 640), 158, 155, 0.97),  # faithful, but under every 2nd frame in a run
        _row("fp32", 1, (384, 512), 134, 137, 0.90),
        _row("fp32", 2, (384, 512), 74, 139, 0.90),
        _row("int8", 1, (384, 512), 93, 92, 0.85),  # disagrees
        _row("int8w7", 1, (384, 512), 98, 98, 0.91),
        _row("int8w7", 2, (384, 512), 45, 81, 0.91),
    ]
    assert _chosen(avx2) == dc.DetectorConfigChoice("int8w7", 2, 384, 512)
    vnni = [
        _row("fp32", 2, (480, 640), 69, 138, 1.0),
        _row("int8", 1, (480, 640), 52, 52, 0.99),
        _row("int8w7", 1, (480, 640), 52, 52, 0.97),
        _row("int8", 1, (384, 512), 35, 35, 0.92),
    ]
    assert _chosen(vnni) == dc.DetectorConfigChoice("int8", 1, 480, 640)


def test_the_doctor_measures_each_copy_the_model_dir_holds(tmp_path: Path) -> None:
    from semmap.runtime.models.model_store import QUANTIZED_FILES

    assert dc.available_precisions(tmp_path) == ["fp32"]
    (tmp_path / QUANTIZED_FILES["int8w7"]).write_bytes(b"")
    assert dc.available_precisions(tmp_path) == ["fp32", "int8w7"]
    (tmp_path / QUANTIZED_FILES["int8"]).write_bytes(b"")
    configs = dc.candidate_configs(dc.available_precisions(tmp_path), cores=2, sizes=[(480, 640)])
    assert [c.label() for c in configs] == ["fp32 640x480 1t", "fp32 640x480 2t", "int8 640x480 1t",
                                            "int8 640x480 2t", "int8w7 640x480 1t", "int8w7 640x480 2t"]  # fmt: skip


def test_on_a_vnni_machine_the_same_rule_keeps_int8() -> None:
    rows = [_row("fp32", 2, (480, 640), 70, 130, 1.0), _row("int8", 2, (480, 640), 30, 55, 0.95),
            _row("int8", 1, (480, 640), 47, 47, 0.95)]  # fmt: skip
    best = dc.choose(rows, cores=2)
    assert best is not None and best.config.precision == "int8"


def test_frame_budget_plan() -> None:
    row = _row("fp32", 1, (384, 512), 90, 90, 0.93)
    plan = dc.plan_cadence(row, cores=2, fps=30.0, others_cpu_ms=30.0)  # others: 0.9 cores
    assert plan.free_cores == pytest.approx(1.1) and plan.interval_ms == pytest.approx(90.0)
    # one thread fits in the 1.1 cores left: offered every 2nd frame, it detects as often as it can (1 / 90 ms)
    assert plan.flat_out and plan.every_n == 2 and plan.detections_per_s == pytest.approx(1e3 / 90)
    slow = dc.plan_cadence(_row("fp32", 1, (384, 512), 105, 105, 0.93), cores=2, fps=30.0, others_cpu_ms=30.0)
    assert slow.every_n == 3 and slow.detections_per_s == pytest.approx(1e3 / 105)
    two = dc.plan_cadence(_row("fp32", 2, (384, 512), 60, 120, 0.93), cores=2, fps=30.0, others_cpu_ms=30.0)
    # two threads do not fit in 1.1 cores: held to its share, every 4th frame (109 ms a detection)
    assert not two.flat_out and two.interval_ms == pytest.approx(120 / 1.1) and two.every_n == 4
    assert two.detections_per_s == 7.5
    loaded = dc.plan_cadence(row, cores=2, fps=30.0, others_cpu_ms=60.0)  # 1.8 cores taken by the others
    assert loaded.free_cores == pytest.approx(0.25) and loaded.every_n == 11  # (never less than a quarter core)
    assert "every 4th frame at 30 fps; expected 7.5 detections/s" in dc.describe_plan(two, "default estimate")
    assert "every 2nd frame at 30 fps, taken as fast as it can (its 1 thread fit" in dc.describe_plan(plan, "x")


# --- the cache, keyed by the machine -----------------------------------------------------------------------

KEY = {"cpu": "AMD EPYC", "flags": ["avx", "avx2", "f16c", "fma"], "cores": 2, "onnxruntime": "1.31.1",
       "providers": ["CPUExecutionProvider"]}  # fmt: skip


def test_cache_is_keyed_by_the_machine(tmp_path: Path) -> None:
    rows = [_row("fp32", 2, (480, 640), 110, 200, 1.0), _row("fp32", 1, (384, 512), 95, 95, 0.93)]
    dc.save_choice(rows, KEY, "7scenes", tmp_path)
    assert dc.cached_choice(tmp_path, KEY).config == dc.DetectorConfigChoice("fp32", 1, 384, 512)
    vnni = {**KEY, "flags": [*KEY["flags"], "avx512_vnni"]}
    assert dc.load_choice(tmp_path, vnni) is None  # another CPU: measure again
    assert dc.load_choice(tmp_path, {**KEY, "onnxruntime": "1.32.0"}) is None  # another runtime: too
    assert dc.load_choice(tmp_path, {**KEY, "cores": 4}) is None
    (tmp_path / dc.CHOICE_FILENAME).write_text("{ not json")
    assert dc.load_choice(tmp_path, KEY) is None


def test_hardware_key_names_the_simd_flags() -> None:
    key = dc.hardware_key()
    assert key["cpu"] and key["cores"] >= 1 and key["onnxruntime"] == ort.__version__
    assert set(key["flags"]) <= set(dc.KEY_FLAGS)
    assert dc.has_vnni({"flags": ["avx2", "avx512_vnni"]}) and not dc.has_vnni(KEY)


def test_auto_in_real_time_takes_the_cached_choice(tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    monkeypatch.setenv("SEMMAP_MODEL_DIR", str(tmp_path))
    none = dc.resolve_setup("auto", 0, "auto", realtime=True)  # not measured here: fp32, full size, 2 threads
    assert (none.precision, none.threads, none.hw, none.measured) == ("fp32", 2, None, None)
    dc.save_choice([_row("fp32", 1, (384, 512), 95, 95, 0.93), _row("int8", 2, (480, 640), 50, 90, 0.8)],
                   dc.hardware_key(), "test", tmp_path)  # fmt: skip
    rt = dc.resolve_setup("auto", 0, "auto", realtime=True)
    assert (rt.precision, rt.threads, rt.hw, rt.origin) == ("fp32", 1, (384, 512), "measured on this machine")
    assert dc.resolve_setup("auto", 2, "416x320", realtime=True).hw == (320, 416)  # explicit settings win
    lock = dc.resolve_setup("auto", 0, "auto", realtime=False)
    assert (lock.precision, lock.threads, lock.hw) == ("fp32", 2, None)  # lockstep: fp32's figures
    assert dc.resolve_setup("int8", 0, "auto", realtime=True).precision == "int8"
    plan, source = dc.setup_plan(rt, 30.0, "gt", tmp_path, cores=2)
    assert plan is not None and plan.every_n == 2 and source == "default estimate"
    assert dc.record_pipeline_cost("rgbd", 50.0, tmp_path)
    plan, source = dc.setup_plan(rt, 30.0, "rgbd", tmp_path, cores=2)
    assert plan.others_cpu_ms == 50.0 and source.startswith("measured")
    dc.save_choice([_row("fp32", 1, (384, 512), 95, 95, 0.93)], dc.hardware_key(), "again", tmp_path)
    assert dc.setup_plan(rt, 30.0, "rgbd", tmp_path, cores=2)[0].others_cpu_ms == 50.0  # kept when re-measured
    assert dc.record_pipeline_cost("gt", 18.0, tmp_path, detector="fp32 512x384 1 thread", detections_per_s=9.4)
    assert dc.last_achieved("gt", "fp32 512x384 1 thread", tmp_path) == 9.4  # shown beside the next expectation
    assert dc.last_achieved("rgbd", "fp32 512x384 1 thread", tmp_path) is None
    # a run played at 3x its recording's speed (the soak) does not speak for the next run at 1x
    assert not dc.record_pipeline_cost("gt", 9.0, tmp_path, detector="fp32 512x384 1 thread", detections_per_s=3.1,
                                       speed=3.0)
    assert dc.last_achieved("gt", "fp32 512x384 1 thread", tmp_path) == 9.4
    # the next plan takes the median of the last runs: one run on a busy machine does not flip the choice
    for cost in (47.0, 53.0, 48.0, 90.0):
        dc.record_pipeline_cost("rgbd", cost, tmp_path)
    assert dc.setup_plan(rt, 30.0, "rgbd", tmp_path, cores=2)[0].others_cpu_ms == 50.0  # of 50, 47, 53, 48, 90
    for cost in (40.0, 41.0, 42.0):
        dc.record_pipeline_cost("rgbd", cost, tmp_path)
    assert dc.setup_plan(rt, 30.0, "rgbd", tmp_path, cores=2)[0].others_cpu_ms == 42.0  # the last 5 only


def test_a_read_only_model_dir_keeps_the_measurement_in_the_choice_dir(tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    """The container image: root's models, the services' user measures into a volume of its own."""
    models, own = tmp_path / "models", tmp_path / "measured"
    models.mkdir()
    monkeypatch.setenv("SEMMAP_MODEL_DIR", str(models))
    monkeypatch.setenv("SEMMAP_CHOICE_DIR", str(own))  # (not made yet: saving makes it)
    path = dc.save_choice([_row("int8w7", 1, (384, 512), 95, 95, 0.93)], dc.hardware_key(), "test")
    assert path == own / dc.CHOICE_FILENAME and not (models / dc.CHOICE_FILENAME).exists()
    rt = dc.resolve_setup("auto", 0, "auto", realtime=True)  # what a detector service started by compose resolves
    assert (rt.precision, rt.hw, rt.origin) == ("int8w7", (384, 512), "measured on this machine")
    assert dc.record_pipeline_cost("gt", 20.0)
    assert json.loads(path.read_text())["pipeline_cpu_ms_per_frame"] == {"gt": 20.0}
    assert dc.choice_path(models) == models / dc.CHOICE_FILENAME  # a model dir given (`--dir`) keeps its own
    monkeypatch.delenv("SEMMAP_CHOICE_DIR")
    assert dc.load_choice() is None  # beside the models again: nothing measured there


# --- semmap models doctor ----------------------------------------------------------------------------------


def test_doctor_prints_the_cached_table_and_the_choice(tmp_path: Path, monkeypatch, capsys) -> None:  # noqa: ANN001
    from semmap.cli.main import main

    monkeypatch.setenv("SEMMAP_MODEL_DIR", str(tmp_path))
    assert main(["models", "doctor"]) == 2  # no model fetched
    (tmp_path / MODEL_FILENAME).write_bytes(b"x")  # (never loaded: the choice is cached for this machine)
    dc.save_choice([_row("fp32", 2, (480, 640), 110, 200, 1.0), _row("fp32", 1, (384, 512), 95, 95, 0.93),
                    _row("int8", 2, (320, 416), 40, 75, 0.74)], dc.hardware_key(), "7scenes", tmp_path)  # fmt: skip
    capsys.readouterr()
    assert main(["models", "doctor"]) == 0
    out = capsys.readouterr().out
    assert "choice (detector.precision auto, real time): fp32 512x384 1t" in out
    assert "int8 416x320 2t" in out and "(disagrees)" in out and "cup 0.74" in out
    assert ("no VNNI" in out) != dc.has_vnni(dc.hardware_key())
    assert main(["models", "doctor", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["choice"]["config"]["height"] == 384


def test_doctor_refuses_a_home_it_cannot_write_before_measuring(tmp_path: Path, monkeypatch, capsys) -> None:  # noqa: ANN001
    from semmap.cli.main import main

    monkeypatch.setenv("SEMMAP_MODEL_DIR", str(tmp_path))
    (tmp_path / MODEL_FILENAME).write_bytes(b"x")  # (never loaded: refused before measuring)
    (tmp_path / "a-file").write_text("")
    monkeypatch.setenv("SEMMAP_CHOICE_DIR", str(tmp_path / "a-file" / "measured"))
    assert main(["models", "doctor"]) == 1
    assert "not writable): set SEMMAP_CHOICE_DIR" in capsys.readouterr().err


def test_summary_reports_the_planned_and_the_achieved_cadence(tmp_path: Path) -> None:
    from semmap.runtime.summary import run_summary

    stats = {"outcome": "completed", "wall_s": 36.0, "frames": {"processed": 1000, "published": 1000},
             "detector_budget": {"detector": "fp32 512x384 1 thread",
                                 "planned": {"every_n_frames": 3, "expected_detections_per_s": 10.0},
                                 "achieved": {"detections_per_s": 9.4, "detect_ms_p50": 97.0}}}  # fmt: skip
    text = run_summary(tmp_path, stats)
    assert ("  detection   planned: fp32 512x384 1 thread, every 3 frame(s), 10.0/s; achieved 9.4/s of video, "
            "detector 97 ms p50 in the run") in text.splitlines()
    assert not any(line.startswith("  fidelity") for line in text.splitlines())  # (none recorded: none said)


def test_a_run_says_what_its_smaller_letterbox_may_miss(tmp_path: Path, monkeypatch, capsys) -> None:  # noqa: ANN001
    """Real time at a smaller letterbox than lockstep's says so at the start and in the summary, with the doctor's
    agreement and small-object recall, so that a map with fewer objects comes with its reason."""
    from semmap.cli.run import detector_budget
    from semmap.core.config import load_config
    from semmap.runtime.summary import run_summary

    monkeypatch.setenv("SEMMAP_MODEL_DIR", str(tmp_path))
    small = dc.Measured(dc.DetectorConfigChoice("fp32", 2, 384, 512), 50, 55, 97, 0.9036, 0.93, 0.88,
                        {"book": 0.889, "chair": 0.99, "cell phone": 0.6, "cup": 1.0}, 0.8379, 47)  # fmt: skip
    full = _row("fp32", 2, (480, 640), 70, 140, 1.0)
    dc.save_choice([full, small], dc.hardware_key(), "test", tmp_path)
    dc.record_pipeline_cost("gt", 18.0, tmp_path)
    config = load_config(None, ["odometry.mode=gt"])
    budget = detector_budget(config, None, "some/folder", [])
    assert budget["detector"].startswith("fp32 512x384")
    assert budget["fidelity"] == {"reference": "fp32 640x480", "f1": 0.9, "f1_strict": 0.84, "recall": 0.93,
                                  "recall_small": {"book": 0.89, "cell phone": 0.6, "cup": 1.0}}  # fmt: skip
    said = "agrees with lockstep's (fp32 640x480) at F1 0.90 (0.84 strictly) on this machine's frames; " \
           "recall book 0.89, cell phone 0.60, cup 1.00: small and far objects that a lockstep run maps may be missing"
    assert f"semmap: real time's detector {said}" in capsys.readouterr().err.splitlines()
    stats = {"outcome": "completed", "wall_s": 36.0, "frames": {"processed": 1000, "published": 1000},
             "detector_budget": {**budget, "achieved": {"detections_per_s": 14.9}}}
    assert f"  fidelity    the detector {said}" in run_summary(tmp_path, stats).splitlines()
    # lockstep's own detector in real time (full size, fp32): nothing to say
    full_size = load_config(None, ["odometry.mode=gt", "detector.precision=fp32", "detector.input_size=640x480"])
    budget = detector_budget(full_size, None, "some/folder", [])
    assert budget["fidelity"]["f1"] == 1.0 and dc.describe_fidelity(budget["fidelity"]) is None
    assert "real time's detector" not in capsys.readouterr().err


# --- layouts: one detector of several threads, or single-thread replicas ----------------------------------


def test_layouts_are_measured_flat_out_beside_a_stand_in_load() -> None:
    """Real processes, a real (tiny) network: each layout detects, and the figures are per second."""
    blob, _ = convert_checkpoint(tiny_checkpoint(nc=3, seed=0), (64, 96))
    images = [np.random.default_rng(i).integers(0, 255, (48, 64, 3), dtype=np.uint8) for i in range(3)]
    layouts = dc.measure_layouts(blob, images, cores=2, load_cores=0.5, seconds=0.5)
    assert [(lay.replicas, lay.threads) for lay in layouts] == [(1, 2), (2, 1)]
    assert all(lay.detections_per_s > 4 and lay.load_cores == 0.5 for lay in layouts)
    assert dc.candidate_layouts(1) == [(1, 1)]  # one core: nothing to share
    assert dc.candidate_layouts(16) == [(1, 2), (2, 1)]  # (each replica holds its own network)


def test_replicas_only_where_measured_better_and_for_the_load_measured(tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    monkeypatch.setenv("SEMMAP_MODEL_DIR", str(tmp_path))
    rows = [_row("fp32", 2, (384, 512), 50, 97, 0.93), _row("fp32", 1, (384, 512), 92, 93, 0.93)]
    layouts = [dc.Layout(1, 2, 14.7, 0.55), dc.Layout(2, 1, 16.8, 0.55)]
    dc.save_choice(rows, dc.hardware_key(), "test", tmp_path, layouts)
    dc.record_pipeline_cost("gt", 18.0, tmp_path)  # 0.54 cores at 30 fps: the load the layouts were measured at
    dc.record_pipeline_cost("rgbd", 37.0, tmp_path)  # 1.1 cores: heavier than that
    setup = dc.resolve_setup("auto", 0, "auto", realtime=True)
    single, _ = dc.setup_plan(setup, 30.0, "gt", tmp_path, cores=2)
    assert single.replicas == 1  # (unless asked for)
    plan, _ = dc.setup_plan(setup, 30.0, "gt", tmp_path, cores=2, replicas=True)
    # 16.8 detections/s of 30 frames: turns of every 2nd frame, each replica every 4th (15/s, evenly spaced)
    assert (plan.replicas, plan.threads, plan.every_n) == (2, 1, 2) and plan.detections_per_s == pytest.approx(15.0)
    assert "2 replicas of 1 thread taking turns, every 2nd frame" in dc.describe_plan(plan, "x")
    assert "1 x 2 threads 14.7/s" in plan.layout_note
    fast = dataclasses.replace(plan, interval_ms=1e3 / 29.8)  # the VNNI EPYC's int8 replicas: every frame
    assert fast.every_n == 1 and fast.detections_per_s == pytest.approx(29.8)
    assert dc.setup_plan(setup, 30.0, "rgbd", tmp_path, cores=2, replicas=True)[0].replicas == 1
    threads_set = dc.resolve_setup("auto", 2, "auto", realtime=True)
    assert dc.setup_plan(threads_set, 30.0, "gt", tmp_path, cores=2, replicas=True)[0].replicas == 1
    assert dc.best_layout([dc.Layout(1, 2, 14.7, 0.5), dc.Layout(2, 1, 15.0, 0.5)]).replicas == 1  # < 5 % better
    doc = dc.load_choice(tmp_path)
    assert "2 x 1 thread 16.8 detections/s" in dc.format_table(doc)
    assert dc.format_table(doc).endswith("fp32 512x384 2t, 2 x 1 thread")


def test_no_replicas_where_the_last_run_starved_the_front_end(tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    """A front end that cannot keep up skips frames, so a run measures the CPU it got, not the CPU it needs: on the
    AVX2 stand-in an `rgbd` run with one detector posed 283 of 1000 frames and measured 1.0 cores of others, within
    the load bound, and the next runs started replicas that left it 192-205 frames. The posed share decides."""
    monkeypatch.setenv("SEMMAP_MODEL_DIR", str(tmp_path))
    rows = [_row("fp32", 2, (384, 512), 50, 97, 0.93), _row("fp32", 1, (384, 512), 92, 93, 0.93)]
    dc.save_choice(rows, dc.hardware_key(), "test", tmp_path, [dc.Layout(1, 2, 11.5, 0.9), dc.Layout(2, 1, 17.5, 0.9)])
    setup = dc.resolve_setup("auto", 0, "auto", realtime=True)
    dc.record_pipeline_cost("gt", 25.0, tmp_path, front_end_share=1.0)
    dc.record_pipeline_cost("rgbd", 34.0, tmp_path, front_end_share=0.283)  # 1.02 cores: within 1.25 x 0.9
    assert dc.setup_plan(setup, 30.0, "gt", tmp_path, cores=2, replicas=True)[0].replicas == 2
    starved = dc.setup_plan(setup, 30.0, "rgbd", tmp_path, cores=2, replicas=True)[0]
    assert starved.replicas == 1
    assert "the last rgbd run here posed 28% of its frames, replicas would starve its odometry" in dc.describe_plan(
        starved, "x")
    dc.record_pipeline_cost("rgbd", 34.0, tmp_path, front_end_share=0.97)  # a machine where it keeps up
    assert dc.setup_plan(setup, 30.0, "rgbd", tmp_path, cores=2, replicas=True)[0].replicas == 2
    assert dc.load_choice(tmp_path)["front_end_posed_share"] == {"gt": 1.0, "rgbd": 0.97}


def test_a_run_starts_the_replicas_its_budget_chose(tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    from semmap.cli.run import detector_budget
    from semmap.core.config import load_config

    monkeypatch.setenv("SEMMAP_MODEL_DIR", str(tmp_path))
    rows = [_row("fp32", 2, (384, 512), 50, 97, 0.93), _row("fp32", 1, (384, 512), 92, 93, 0.93)]
    layouts = [dc.Layout(1, 2, 14.7, 0.55), dc.Layout(2, 1, 16.8, 0.55)]
    dc.save_choice(rows, dc.hardware_key(), "test", tmp_path, layouts)
    dc.record_pipeline_cost("gt", 18.0, tmp_path)
    config = load_config(None, ["odometry.mode=gt"])
    overrides: list[str] = []
    budget = detector_budget(config, None, "some/folder", overrides)
    assert budget["replicas"] == 2 and "detector.threads=1" in overrides and "detector.every_n_frames=2" in overrides
    assert budget["detector"] == "fp32 512x384 1 thread x 2 replicas"
    overrides = []
    budget = detector_budget(config, None, "some/folder", overrides, detectors=1)  # --detectors 1: one
    assert "replicas" not in budget and not any(o.startswith("detector.threads") for o in overrides)


def test_replicas_set_by_hand_are_planned_together_taking_turns(tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    """`--detectors 2` with the cadence left to the budget: a plan for the two, not one detector's every 2nd frame
    (which left each replica a quarter of the frames and half the cores idle)."""
    from semmap.cli.run import detector_budget
    from semmap.core.config import load_config

    monkeypatch.setenv("SEMMAP_MODEL_DIR", str(tmp_path))
    rows = [_row("fp32", 2, (384, 512), 50, 97, 0.93), _row("fp32", 1, (384, 512), 92, 93, 0.93)]
    dc.save_choice(rows, dc.hardware_key(), "test", tmp_path, [dc.Layout(1, 2, 14.7, 0.55)])
    dc.record_pipeline_cost("gt", 18.0, tmp_path)  # the others: 0.54 cores, 1.46 left
    config = load_config(None, ["odometry.mode=gt", "detector.precision=fp32", "detector.threads=1",
                                "detector.input_size=512x384"])  # fmt: skip
    overrides: list[str] = []
    alone = detector_budget(config, None, "some/folder", overrides)
    assert "detector.every_n_frames=2" in overrides and "replicas" not in alone  # one: 92 ms, every 2nd frame
    overrides = []
    budget = detector_budget(config, None, "some/folder", overrides, detectors=2)
    assert "detector.every_n_frames=2" in overrides and budget["replicas"] == 2  # (taking turns)
    # together: two 1-thread replicas in the 1.46 cores left, 93 ms CPU a detection: 15.7/s, turns of 2 frames
    assert budget["planned"]["interval_ms"] == pytest.approx(93 / 1.46, abs=0.1)
    assert budget["planned"]["expected_detections_per_s"] == 15.0
    assert budget["detector"] == "fp32 512x384 1 thread x 2 replicas"
    plan = dc.replicas_by_hand(dc.plan_cadence(rows[1], cores=2, fps=30.0, others_cpu_ms=0.0), 93.0, 2)
    assert plan.interval_ms == pytest.approx(46.5) and plan.every_n == 1  # two idle cores: twice one alone
    assert plan.detections_per_s == pytest.approx(1e3 / 46.5)


def test_a_run_rechooses_for_its_front_ends_measured_cost(tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    """The doctor plans for `gt`'s 30 ms of the other services a frame: full-size fp32 then detects every 2nd
    frame. A front end measured at 45 ms leaves 0.6 cores: fp32 would be held to every 4th frame, and the as
    faithful int8 at the same size detects twice as often for the same CPU, so the run takes it. ORB-SLAM3 never
    measured here plans with its default estimate (48 ms) from the first run on; a front end with neither figure
    (`file:`), or a setup given, keeps the doctor's choice."""
    monkeypatch.setenv("SEMMAP_MODEL_DIR", str(tmp_path))
    rows = [_row("fp32", 2, (480, 640), 35, 64, 1.0), _row("int8", 1, (480, 640), 31, 31, 0.98),
            _row("int8", 2, (384, 512), 12, 22, 0.85)]  # (the last disagrees: F1 under 0.9)
    dc.save_choice(rows, dc.hardware_key(), "test", tmp_path)
    setup = dc.resolve_setup("auto", 0, "auto", realtime=True)
    assert (setup.precision, setup.hw) == ("fp32", (480, 640))  # the doctor's choice
    first = dc.for_front_end(setup, "orbslam3", tmp_path)  # not measured here yet: its default estimate
    assert (first.precision, first.threads, first.hw) == ("int8", 1, (480, 640))
    assert first.origin.endswith("(orbslam3: 48 ms a frame, default estimate)")
    assert dc.for_front_end(setup, "file:/tmp/slam.tum", tmp_path) is setup  # no figure for an external SLAM
    assert dc.record_pipeline_cost("orbslam3", 45.0, tmp_path)
    chosen = dc.for_front_end(setup, "orbslam3", tmp_path)
    assert (chosen.precision, chosen.threads, chosen.hw) == ("int8", 1, (480, 640))
    assert chosen.origin.startswith(dc.MEASURED_FOR_FRONT_END) and chosen.measured is not None
    plan, _ = dc.setup_plan(chosen, 30.0, "orbslam3", tmp_path, cores=2)
    assert plan is not None and plan.every_n == 2
    given = dc.resolve_setup("fp32", 2, "640x480", realtime=True)
    assert dc.for_front_end(given, "orbslam3", tmp_path) is given  # settings given are kept
