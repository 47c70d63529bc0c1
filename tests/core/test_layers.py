"""The layer contracts (pyproject.toml, [tool.importlinter]): cli -> services -> runtime -> algorithms -> datasets
-> imaging -> core, imports pointing down only, and core never imports OpenCV. import-linter reads the static import
graph, deferred imports included."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

PROJECT = Path(__file__).resolve().parents[2]


def test_layers_point_one_way() -> None:
    lint = Path(sys.executable).parent / "lint-imports"
    result = subprocess.run([str(lint), "--config", "pyproject.toml", "--no-cache"], cwd=PROJECT, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]


def test_no_top_level_modules_outside_the_layers() -> None:
    """Every module lives in a layer package, so the contract above sees all of them."""
    stray = sorted(p.name for p in (PROJECT / "semmap").glob("*.py") if p.name != "__init__.py")
    assert stray == [], stray


def test_messages_travel_without_opencv() -> None:
    """Core never loads OpenCV, even at run time: every message kind encodes and decodes (frames too, their
    images left encoded) in a process where `cv2` cannot be imported at all."""
    script = (
        "from tests.core.test_messages import _samples\n"
        "for m in _samples(): type(m).decode(m.encode())\n"
        "assert sys.modules['cv2'] is None\n"
    )
    stub = (  # the samples build a frame from arrays, which needs a codec: a stub one, installed first
        "import sys; sys.modules['cv2'] = None\n"  # any `import cv2` now raises ImportError
        "from semmap.core.messages import use_image_codec\n"
        "class Stub:\n"
        "    def encode_jpeg(self, rgb, quality): return b'\\xff\\xd8stub'\n"
        "    def decode_jpeg(self, data): return None\n"
        "    def encode_png16(self, image): return None\n"
        "    def decode_png16(self, data): return None\n"
        "use_image_codec(Stub())\n"
    )
    result = subprocess.run([sys.executable, "-c", stub + script], cwd=PROJECT, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
