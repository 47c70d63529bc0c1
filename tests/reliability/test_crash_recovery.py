"""SIGKILL services in the middle of a run: `semmap run` restarts them, the run completes, nothing mapped is lost,
and the final map matches a clean run's within a stated tolerance."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

PROJECT = Path(__file__).resolve().parents[2]
DATA = "synthetic:frames=240"
# a landmark of the clean map has a same-class landmark this close in the map of the run with crashes
CENTROID_TOLERANCE_M = 0.10


def _command(out: Path) -> list[str]:
    return [sys.executable, "-m", "semmap.cli", "run", DATA, "--out", str(out), "--odometry", "gt+drift", "--seed",
            "2", "--no-viz"]


def _landmarks(out: Path) -> list[dict]:
    return json.loads((out / "map.json").read_text())["landmarks"]


class _Run:
    """`semmap run` in the background, with the pids of its services read from its log lines."""

    def __init__(self, out: Path) -> None:
        self.proc = subprocess.Popen(_command(out), cwd=PROJECT, stderr=subprocess.PIPE, text=True,
                                     env={**os.environ, "CI": "true"})
        self.pids: dict[str, int] = {}
        self.log: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.log.append(line)
            m = re.search(r"(?:started|restarted) ([a-z]+)(?: \(restart \d+,)? ?\(?pid (\d+)\)", line)
            if m:
                self.pids[m.group(1)] = int(m.group(2))


def _kill_in_turn(tmp_path: Path, victims: list[str]) -> None:
    clean = tmp_path / "clean"
    result = subprocess.run(_command(clean), cwd=PROJECT, capture_output=True, text=True, timeout=600,
                            env={**os.environ, "CI": "true"})
    assert result.returncode == 0, result.stderr[-3000:]

    crashed = tmp_path / "crashed"
    run = _Run(crashed)
    before: dict[str, set[int]] = {}
    try:
        deadline = time.monotonic() + 120
        while not (crashed / "map.json").is_file() and time.monotonic() < deadline:
            time.sleep(0.2)
        for victim in victims:
            time.sleep(3.0)
            assert run.proc.poll() is None, "".join(run.log[-30:])
            before[victim] = {lm["id"] for lm in _landmarks(crashed)}
            os.kill(run.pids[victim], signal.SIGKILL)
        assert run.proc.wait(timeout=600) == 0, "".join(run.log[-40:])
    finally:
        if run.proc.poll() is None:
            run.proc.kill()
    stats = json.loads((crashed / "stats.json").read_text())
    assert stats["outcome"] == "completed" and stats["restarts"] == len(victims)
    assert stats["frames"]["processed"] == 240

    final = _landmarks(crashed)
    final_ids = {lm["id"] for lm in final}
    merged_away = _merged_ids(crashed)
    for victim, ids in before.items():
        lost = ids - final_ids - merged_away
        assert not lost, f"landmarks {lost} mapped before {victim} was killed are gone"

    reference = _landmarks(clean)
    assert abs(len(final) - len(reference)) <= 1
    for lm in reference:
        same = [o for o in final if o["class"] == lm["class"]]
        assert same, f"no {lm['class']} after the crashes"
        nearest = min(np.linalg.norm(np.subtract(o["centroid"], lm["centroid"])) for o in same)
        assert nearest <= CENTROID_TOLERANCE_M, f"{lm['class']} #{lm['id']} moved {nearest:.3f} m"


def _merged_ids(out: Path) -> set[int]:
    """Ids the associator merged into others (legitimately gone), from its log."""
    text = (out / "logs" / "associator.log").read_text() if (out / "logs" / "associator.log").is_file() else ""
    return {int(m) for m in re.findall(r"merged landmark (\d+) into", text)}


def test_killing_the_stateful_services_loses_nothing(tmp_path: Path) -> None:
    _kill_in_turn(tmp_path, ["associator", "backend"])


@pytest.mark.slow
def test_killing_every_service_in_turn(tmp_path: Path) -> None:
    _kill_in_turn(tmp_path, ["odometry", "detector", "tracker", "associator", "backend", "player"])
