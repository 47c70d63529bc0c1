"""The closed loop in one process: a thin caller of the in-process driver (semmap/runtime/pipeline/inprocess.py).

    python benchmarks/closed_loop.py DATA [--odometry gt+drift] [--seed N] [--frames N] [--set sec.key=val]...
        [--refresh-cache] [--cache-dir DIR] [--json-out FILE] [--out DIR] [-v]

Same as `python -m semmap.runtime.pipeline.inprocess`; kept because docs/RESULTS.md names this command.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from semmap.runtime.pipeline.inprocess import main  # noqa: E402

if __name__ == "__main__":
    raise SystemExit(main())
