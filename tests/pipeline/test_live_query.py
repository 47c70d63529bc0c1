"""`semmap query` answers while a run lives: each query is a fresh process with a fresh Zenoh session,
which does not yet know the associator's queryable when it first asks; it asks again within its timeout instead
of failing after ~2 s (asking once, 10 of 20 queries failed here)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

PROJECT = Path(__file__).resolve().parents[2]


def _live_queries(tmp_path: Path, count: int) -> list[str]:
    """Start a long synthetic run, ask its map `count` times, one `semmap query` process each; the failures."""
    out, log = tmp_path / "run", tmp_path / "run.stderr"
    env = {**os.environ, "CI": "true"}
    with open(log, "w") as err:
        run = subprocess.Popen([sys.executable, "-m", "semmap.cli", "run", "synthetic:frames=3000", "--out", str(out),
                                "--no-viz", "--quiet"], cwd=PROJECT, stdout=subprocess.DEVNULL, stderr=err, env=env)
    try:
        deadline = time.monotonic() + 180
        endpoint = None
        while time.monotonic() < deadline and run.poll() is None:
            found = re.search(r"bus: (tcp/[0-9.]+:\d+)", log.read_text())
            player = out / "logs" / "player.log"
            if found and player.is_file() and "pipeline ready" in player.read_text():
                endpoint = found.group(1)
                break
            time.sleep(0.3)
        assert endpoint is not None, log.read_text()[-3000:]
        failures = []
        for i in range(count):
            result = subprocess.run([sys.executable, "-m", "semmap.cli", "query", "--connect", endpoint, "--timeout",
                                     "10", "--json"], cwd=PROJECT, capture_output=True, text=True, env=env, timeout=60)
            if result.returncode != 0 or '"landmarks"' not in result.stdout:
                failures.append(f"query {i}: exit {result.returncode}: {result.stderr.strip()}")
        assert run.poll() is None, "the run ended before the queries did"
        return failures
    finally:
        run.send_signal(signal.SIGINT)
        run.wait(timeout=60)


def test_live_queries_answer_while_the_run_lives(tmp_path: Path) -> None:
    assert _live_queries(tmp_path, 5) == []


@pytest.mark.slow
def test_twenty_live_queries_twenty_answers(tmp_path: Path) -> None:
    assert _live_queries(tmp_path, 20) == []
