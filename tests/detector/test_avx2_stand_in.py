"""The doctor's agreement facts on an AVX2-only CPU, real or stood in.

Machines are lent by chance, and on one with AVX-512 and VNNI the AVX2 path of `semmap models doctor` runs
nowhere: were its tie margin to break (a lowered threshold no longer reaching the decode), no test there would see
that on an AVX2-only CPU no smaller letterbox agrees any more and real time falls back to 640x480.
benchmarks/avx2_stand_in.py makes onnxruntime take the AVX2 kernels on a CPU with AVX-512, AVX-VNNI or AMX (and
changes nothing on an AVX2-only one; it also turns off AVX-VNNI and AMX, which an Intel Xeon may have), so these
facts are checked on either class: without VNNI the int8 copy with 8-bit weights disagrees
with fp32 and the one with 7-bit weights (int8w7) agrees, and fp32 512x384 agrees only because a score within 0.1
of the threshold counts as a tie. Scores only; nothing is timed.
"""

from __future__ import annotations

import inspect
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

from semmap.runtime.models import detector_choice as dc
from semmap.runtime.models.model_store import QUANTIZED_FILES, get_model_dir

PROJECT = Path(__file__).resolve().parents[2]

MEASURE = """
import json, sys
import onnxruntime
from pathlib import Path
from semmap.runtime.models import detector_choice as dc
assert onnxruntime.__file__.startswith(sys.argv[1]), onnxruntime.__file__  # the stand-in, not the installed one
images, _ = dc.calibration_images(sys.argv[2], 48)
configs = [dc.DetectorConfigChoice("fp32", 1, 384, 512), dc.DetectorConfigChoice("int8", 1, 480, 640),
           dc.DetectorConfigChoice("int8w7", 1, 480, 640)]
rows = dc.measure_configs(images, configs, timing_frames=1, model_dir=Path(sys.argv[3]))
print(json.dumps({r.config.label(): [r.f1, r.f1_strict, r.recall_per_class] for r in rows}))
print(json.dumps(int8w7_boxes(images[::8], Path(sys.argv[3]))))
"""



def int8w7_boxes(images: list, model_dir: Path) -> list[list[str]]:
    """The int8w7 copy's boxes at 640x480, exactly (run here, and in the stand-in's process from its source)."""
    from semmap.algorithms.detector.onnx_detector import OnnxDetector
    from semmap.runtime.models import detector_choice as dc

    det = OnnxDetector(dc.model_bytes("int8w7", (480, 640), model_dir), threads=1)
    return [[repr(b) for b in det.detect(img)] for img in images]


def _flags() -> set[str]:
    return set(dc.hardware_key()["flags"])


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="an x86-64 CPU's kernels")
def test_without_vnni_int8_disagrees_int8w7_agrees_and_512x384_agrees_by_its_ties(
    kitchen_dir: Path, tmp_path: Path
) -> None:
    flags = _flags()
    if "avx2" not in flags:
        pytest.skip("no AVX2: the stand-in is for AVX2 CPUs")
    models = get_model_dir()
    if not all((models / name).is_file() for name in ("yolov5s.onnx", *QUANTIZED_FILES.values())):
        pytest.skip("detector models absent: run ./dev.sh setup (semmap models fetch / quantize)")
    ort = tmp_path / "ort"
    built = subprocess.run([sys.executable, str(PROJECT / "benchmarks" / "avx2_stand_in.py"), "--out", str(ort)],
                           capture_output=True, text=True, timeout=300)  # fmt: skip
    assert built.returncode == 0, built.stderr
    env = dict(os.environ, PYTHONPATH=str(ort))
    script = "from pathlib import Path\n" + inspect.getsource(int8w7_boxes) + MEASURE
    done = subprocess.run([sys.executable, "-c", script, str(ort), str(kitchen_dir), str(models)], env=env,
                          capture_output=True, text=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    scores = json.loads(done.stdout.strip().splitlines()[-2])
    f1, strict, _ = scores["fp32 512x384 1t"]
    assert strict < dc.AGREEMENT_F1 <= f1, scores  # it agrees, and only by counting the ties at the threshold
    int8_f1, _, per_class = scores["int8 640x480 1t"]
    assert int8_f1 < dc.AGREEMENT_F1, scores  # 8-bit products without VNNI saturate: int8 is never chosen
    assert per_class["book"] < 0.9, per_class  # (small objects lose most)
    w7_f1, w7_strict, _ = scores["int8w7 640x480 1t"]
    assert w7_strict > int8_f1 and w7_f1 >= dc.AGREEMENT_F1, scores  # 7-bit weights cannot saturate: it agrees
    # and with nothing saturating, every integer kernel computes the same sums: its boxes are this CPU's own, to the
    # last bit, wherever this CPU has VNNI or AMX (on an AVX2-only CPU both sides run the same kernels)
    images, _ = dc.calibration_images(kitchen_dir, 48)
    assert json.loads(done.stdout.strip().splitlines()[-1]) == int8w7_boxes(images[::8], models)
