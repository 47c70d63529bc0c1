"""benchmarks/bench_schedule.py, the prediction of what a real-time run maps from its detection time, run as a user
runs it (a separate process) on the synthetic scene: a plan that keeps up maps what lockstep maps, nearly, and a
starved one maps far less."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_a_plan_that_keeps_up_maps_more_than_a_starved_one(tmp_path: Path) -> None:
    out = tmp_path / "schedule.json"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_schedule.py"), "synthetic:frames=90",
         "--plan", "640x480:2:2:50",  # 2 replicas of 50 ms at every 2nd frame: every planned frame detected
         "--plan", "640x480:1:1:200",  # 1 detector of 200 ms: one frame in six
         "--seeds", "2", "--cache-dir", str(tmp_path / "cache"), "--json-out", str(out)],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    keeps_up, starved = json.loads(out.read_text())
    reference = keeps_up["reference"]
    assert reference >= 8  # the synthetic room's objects, every frame detected
    assert keeps_up["detections_per_s"] == [15.0, 15.0]  # no turn lost: exactly every 2nd frame at 30 Hz
    assert starved["detections_per_s"][0] < 6.0
    assert min(keeps_up["landmarks"]) >= 0.8 * reference
    assert max(starved["landmarks"]) < min(keeps_up["landmarks"])
    assert "reference: lockstep at 640x480" in proc.stdout
