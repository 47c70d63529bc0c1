"""The layer contract (pyproject.toml, [tool.importlinter]): cli -> services -> runtime -> algorithms -> datasets
-> core, imports pointing down only. import-linter reads the static import graph, deferred imports included."""

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
