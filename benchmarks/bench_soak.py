"""Soak benchmark: a long lockstep run (7-Scenes played N times) and whether per-frame cost stays flat.

    .venv/bin/python benchmarks/bench_soak.py [--loops 10] [--block 1000] [--out DIR] [--json-out FILE]
        [--set section.key=value]...

Runs the real pipeline (`semmap run 7-Scenes --lockstep --odometry gt+drift --no-viz`, int8 detector on every
3rd frame) with `run.loops=N`, so every place is revisited N times, and listens on the
run's bus from a separate Zenoh session (raw samples: nothing is decoded except the backend's corrected poses
and the associator's map updates, whose messages carry the stage timings). It prints, per block of `--block`
frames:
- throughput (frames per second of wall time, from the backend's messages),
- p50 / p95 of the backend's iSAM2 update, loop-closure step (keyframes), corrected-poses delta, the
  associator's refinement and the end-to-end latency (a frame's publication to its map update),
- bytes per frame on `poses/corrected`;
then the bytes per second on every key over the whole run and each service's peak RSS (stats.json).
Figures depend on the machine's load: compare blocks within one run.
"""

from __future__ import annotations

import argparse
import json
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

PROJECT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(PROJECT))

from semmap.core.messages import CorrectedPoses, MapUpdate, MessageError  # noqa: E402
from semmap.datasets import find_data_root  # noqa: E402
from semmap.runtime.transport.bus import BusConfig, open_session  # noqa: E402

SETTINGS = ["detector.precision=int8", "detector.every_n_frames=3"]
STAGES = (
    ("update", "backend update (iSAM2)"),
    ("loop_closure", "loop-closure step (keyframes)"),
    ("publish", "corrected-poses delta"),
    ("refine", "associator refinement"),
    ("end_to_end", "end to end"),
)
BUS_LINE = re.compile(r"bus: (tcp/[0-9.]+:[0-9]+)")


class Listener:
    """Counts bytes per key and collects per-frame stage timings from the run's messages."""

    def __init__(self, endpoint: str, robot: str) -> None:
        self.prefix = f"semmap/v1/{robot}/"
        self.session = open_session(BusConfig(mode="peer", connect=[endpoint], listen=[]))
        self.lock = threading.Lock()
        self.bytes: dict[str, int] = defaultdict(int)
        self.first_at: float | None = None
        self.last_at = 0.0
        # frame id -> {stage: ms}, {"received": wall time}, {"corrected_bytes": n}
        self.frames: dict[int, dict[str, float]] = defaultdict(dict)
        self.undecodable = 0
        self.sub = self.session.declare_subscriber(f"{self.prefix}**", self._on_sample)

    def _on_sample(self, sample) -> None:  # noqa: ANN001 - zenoh.Sample
        now = time.time()
        key = str(sample.key_expr)[len(self.prefix) :]
        payload = sample.payload.to_bytes()
        with self.lock:
            self.first_at = self.first_at or now
            self.last_at = now
            self.bytes[key.split("/")[0] if key.startswith(("status", "progress")) else key] += len(payload)
        try:
            if key == "poses/corrected":
                msg = CorrectedPoses.decode(payload)
                with self.lock:
                    row = self.frames[msg.frame_id]
                    row.update({k: v for k, v in msg.timing_ms.items() if k in ("update", "loop_closure", "publish")})
                    row["corrected_bytes"] = row.get("corrected_bytes", 0) + len(payload)
                    row["received"] = now
            elif key == "map/updates":
                msg = MapUpdate.decode(payload)
                with self.lock:
                    row = self.frames[msg.frame_id]
                    if "refine" in msg.timing_ms:
                        row["refine"] = msg.timing_ms["refine"]
                    if msg.frame_sent_at > 0:
                        row["end_to_end"] = (now - msg.frame_sent_at) * 1e3
        except MessageError:
            with self.lock:
                self.undecodable += 1

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def percentiles(values: list[float]) -> tuple[float, float] | None:
    if not values:
        return None
    a = np.asarray(values)
    return float(np.percentile(a, 50)), float(np.percentile(a, 95))


def blocks(frames: dict[int, dict[str, float]], size: int) -> list[dict]:
    out = []
    for start in range(0, (max(frames) + 1) if frames else 0, size):
        rows = [frames[f] for f in range(start, start + size) if f in frames]
        received = sorted(r["received"] for r in rows if "received" in r)
        block = {
            "frames": f"{start}-{start + size - 1}",
            "n": len(rows),
            "fps": (len(received) - 1) / (received[-1] - received[0]) if len(received) > 1 else 0.0,
            "corrected_bytes_per_frame": float(np.mean([r.get("corrected_bytes", 0) for r in rows])),
        }
        for stage, _ in STAGES:
            block[stage] = percentiles([r[stage] for r in rows if stage in r])
        out.append(block)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--loops", type=int, default=10)
    ap.add_argument("--block", type=int, default=1000)
    ap.add_argument("--out", type=Path, default=None, help="the run's output folder (default: a temporary one)")
    ap.add_argument("--json-out", type=Path, default=None)
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument(
        "--budget",
        type=float,
        default=6 * 3600.0,
        help="stop the run (Ctrl-C, outputs kept) after this many seconds and print what it measured",
    )
    args = ap.parse_args()
    root = find_data_root()
    data = root / "7scenes-redkitchen" if root is not None else None
    if data is None or not data.exists():
        print("skipped: no 7scenes-redkitchen in ../shared/data or $SEMMAP_DATA", file=sys.stderr)
        return 0
    out = args.out or Path(tempfile.mkdtemp(prefix="semmap-soak-"))
    settings = [*SETTINGS, f"run.loops={args.loops}", *args.overrides]
    cmd = [
        sys.executable,
        "-m",
        "semmap.cli",
        "run",
        str(data),
        "--out",
        str(out),
        "--odometry",
        "gt+drift",
        "--lockstep",
        "--no-viz",
        "--quiet",
    ]
    for s in settings:
        cmd += ["--set", s]
    print("running:", " ".join(cmd[2:]), file=sys.stderr)
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=PROJECT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    listener = None
    tail: list[str] = []
    interrupted = False
    # over budget (or Ctrl-C here): stop the run as Ctrl-C does (every service writes what it has), then report
    timer = threading.Timer(args.budget, lambda: proc.send_signal(signal.SIGINT))
    timer.start()
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            tail = [*tail[-40:], line]
            m = BUS_LINE.search(line)
            if m and listener is None:
                listener = Listener(m.group(1), "robot1")
        rc = proc.wait()
    except KeyboardInterrupt:
        proc.send_signal(signal.SIGINT)
        rc = proc.wait()
    finally:
        timer.cancel()
        if proc.poll() is None:
            proc.kill()
        if listener is not None:
            listener.close()
    wall = time.monotonic() - t0
    stats_path = out / "stats.json"
    interrupted = stats_path.exists() and json.loads(stats_path.read_text()).get("outcome") == "interrupted"
    if (rc != 0 and not interrupted) or listener is None:
        print("".join(tail), file=sys.stderr)
        print(f"the run failed (exit {rc})" if rc else "never saw the run's bus endpoint", file=sys.stderr)
        return 1
    stats = json.loads(stats_path.read_text())
    table = blocks(dict(listener.frames), args.block)
    span = max(listener.last_at - (listener.first_at or listener.last_at), 1e-9)
    result = {
        "loops": args.loops,
        "interrupted": interrupted,
        "settings": settings,
        "wall_s": wall,
        "fps": stats.get("fps"),
        "frames": stats.get("frames"),
        "blocks": table,
        "bytes_per_s": {k: v / span for k, v in sorted(listener.bytes.items())},
        "rss_mb": {
            name: {"peak": s.get("peak_rss_mb"), "early": s.get("rss_early_mb"), "late": s.get("rss_late_mb")}
            for name, s in stats.get("services", {}).items()
        },
        "undecodable": listener.undecodable,
    }
    note = " (stopped early: over budget)" if interrupted else ""
    print(f"\n7-Scenes x{args.loops}{note} ({len(listener.frames)} frames), lockstep, {', '.join(settings)}")
    print(f"wall {wall:.0f} s, {stats.get('fps')} fps overall\n")
    head = f"| frames | fps | {' | '.join(label + ' p50 / p95 ms' for _, label in STAGES)} | poses/corrected B/frame |"
    print(head)
    print("|" + "---|" * (len(STAGES) + 3))
    for b in table:
        cells = [f"{b[s][0]:.1f} / {b[s][1]:.1f}" if b[s] else "-" for s, _ in STAGES]
        print(f"| {b['frames']} | {b['fps']:.1f} | {' | '.join(cells)} | {b['corrected_bytes_per_frame']:.0f} |")
    print("\n| key | bytes/s |\n|---|---|")
    for key, rate in result["bytes_per_s"].items():
        print(f"| `{key}` | {rate:,.0f} |")
    print("\n| service | peak RSS MB | RSS early / late MB |\n|---|---|---|")
    for name, r in result["rss_mb"].items():
        print(f"| {name} | {r['peak']} | {r['early']} / {r['late']} |")
    if args.json_out:
        args.json_out.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
