"""`semmap` finds its commands: each module of semmap.cli with `register(subparsers)` adds its own."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from semmap.cli.main import build_parser, command_modules

PROJECT = Path(__file__).resolve().parents[2]
COMMANDS = {"run", "view", "ros2", "config", "diff", "merge", "eval", "models", "detect", "query", "export"}


def test_every_command_module_registers_itself() -> None:
    names = [m.__name__.rsplit(".", 1)[1] for m in command_modules()]
    assert names[0] == "run"  # ORDER: first in the help
    assert {"run", "view", "ros2", "config", "diff_merge", "evaluate", "models", "query_export"} <= set(names)
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert set(sub.choices) == COMMANDS


def test_help_lists_the_commands_without_importing_their_machinery() -> None:
    """`semmap --help` imports no handler's dependencies (Zenoh, numpy, OpenCV, the algorithms)."""
    code = (
        "import sys; from semmap.cli.main import build_parser; build_parser().format_help(); "
        "print(sorted(m for m in ('zenoh', 'numpy', 'cv2', 'scipy', 'pydantic', 'semmap.algorithms', "
        "'semmap.runtime', 'semmap.services') if m in sys.modules))"
    )
    result = subprocess.run([sys.executable, "-c", code], cwd=PROJECT, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stdout.strip() == "[]", result.stdout + result.stderr
    result = subprocess.run(
        [sys.executable, "-m", "semmap.cli", "--help"], cwd=PROJECT, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0 and all(f"    {name}" in result.stdout for name in COMMANDS), result.stdout


def test_unknown_options_are_still_refused() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "semmap.cli", "eval", "x", "--bogus"],
        cwd=PROJECT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and "unrecognized arguments: --bogus" in result.stderr


def test_ros2_passes_its_options_to_the_bridge() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "semmap.cli", "ros2", "--help"], cwd=PROJECT, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0 and "--robot" in result.stdout and "--connect" in result.stdout, result.stderr
