"""Memory of a service that takes a real-time frame stream it cannot keep up with (the detector's case), in
seconds instead of a soak run's minutes.

    .venv/bin/python benchmarks/bench_memory.py [--seconds 40] [--rate 90] [--work-ms 300] [--frames 30]
        [--variant callback|latest]...

Two processes on a loopback Zenoh bus, signed as in a `semmap run` (RunTrust): a publisher sends real 7-Scenes
frames (`--frames` of them, encoded once, over and over) at `--rate` Hz; a subscriber takes them the way a
service does in real time (`Bus.subscribe` -> `Inbox` of capacity 1: the newest frame waits, older ones are
dropped) and its main thread spends `--work-ms` on each frame it takes (decodes colour and depth, then busy
CPU: a detector on a loaded machine). It prints the subscriber's RSS every 5 s, its growth from the first
sample after warm-up (10 s) to the last, how many frames it took and dropped and how old the frames it took
were. Variants (each a fresh pair of processes; default: both):
- `callback`: a subscription with a Python callback (Zenoh queues up to 256 samples for it on a thread of its
  own, so a slow reader's memory grows),
- `latest`: `Bus.subscribe(..., latest=1)` as `Service.listen` does for real-time streams.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

PROJECT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(PROJECT))

from semmap.core.messages import Frame  # noqa: E402
from semmap.runtime.orchestrator import free_loopback_port  # noqa: E402
from semmap.runtime.transport.bus import ENV_RUN_ID, ENV_RUN_KEY, Bus, BusConfig, Inbox, RunTrust  # noqa: E402
from semmap.runtime.transport.service import rss_mb  # noqa: E402

ROBOT = "robot1"
WARMUP_S = 10.0
VARIANTS = ("callback", "latest")


def publish(endpoint: str, frames: int, rate: float, seconds: float) -> None:
    from semmap.datasets import find_data_root, open_dataset
    from semmap.services.player.service import frame_message

    root = find_data_root()
    if root is None:
        raise SystemExit("no data root (../shared/data): 7-Scenes frames are needed")
    data = open_dataset(root / "7scenes-redkitchen")
    messages = [frame_message(ROBOT, data[i * 7 % len(data)]) for i in range(frames)]
    bus = Bus(BusConfig(mode="peer", connect=[], listen=[endpoint]), ROBOT, RunTrust.from_env("player"))
    pub = bus.publisher(bus.keys.frames)
    if not pub.wait_matching(30.0):
        raise SystemExit("the subscriber did not come")
    start = time.monotonic()
    n = 0
    while time.monotonic() - start < seconds:
        message = messages[n % len(messages)]
        message.frame_id = n
        pub.put(message)
        n += 1
        time.sleep(max(0.0, start + n / rate - time.monotonic()))
    bus.close()


def subscribe(endpoint: str, seconds: float, work_ms: float, variant: str) -> None:
    bus = Bus(BusConfig(mode="peer", connect=[endpoint], listen=[]), ROBOT, RunTrust.from_env("detector"))
    inbox = Inbox()
    inbox.add_stream("frames", 1)  # as Service.listen(..., realtime_capacity=detector.queue) in real time
    bus.subscribe(
        bus.keys.frames,
        Frame,
        lambda frame: inbox.put("frames", frame),
        latest=1 if variant.startswith("latest") else None,
    )
    start = time.monotonic()
    taken, samples, ages = 0, [], []
    next_sample = start
    while time.monotonic() - start < seconds:
        item = inbox.get(0.1)
        if item is not None:
            frame = item[1]
            ages.append(time.time() - frame.sent_at)
            frame.rgb(), frame.depth()
            busy_until = time.perf_counter() + work_ms / 1e3
            while time.perf_counter() < busy_until:
                pass
            taken += 1
            del frame, item
        if time.monotonic() >= next_sample:
            samples.append((time.monotonic() - start, rss_mb()))
            next_sample += 5.0
    bus.close()
    after = [mb for t, mb in samples if t >= WARMUP_S]
    dropped = inbox.dropped["frames"] + sum(bus.dropped.values())
    ages.sort()
    print(f"  {variant:<14} RSS MB " + " ".join(f"{t:.0f}s:{mb:.0f}" for t, mb in samples))
    print(
        f"  {'':<14} growth after {WARMUP_S:.0f} s: {after[-1] - after[0]:+.1f} MB, "
        f"peak {max(m for _, m in samples):.0f} MB; "
        f"frames taken {taken}, dropped {dropped}; age of a frame taken p50 {1e3 * ages[len(ages) // 2]:.0f} ms",
        flush=True,
    )


def run_pair(args: argparse.Namespace, variant: str) -> None:
    port = free_loopback_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    env = {**os.environ, ENV_RUN_ID: "bench-memory", ENV_RUN_KEY: RunTrust.new_secret()}
    env.pop("MALLOC_MMAP_THRESHOLD_", None)
    common = [sys.executable, __file__, "--endpoint", endpoint, "--seconds", str(args.seconds)]
    pub = subprocess.Popen([*common, "--role", "pub", "--rate", str(args.rate), "--frames", str(args.frames)], env=env)
    sub = subprocess.Popen([*common, "--role", "sub", "--work-ms", str(args.work_ms), "--variant", variant], env=env)
    sub.wait(args.seconds + 120)
    pub.wait(30)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=40.0)
    parser.add_argument("--rate", type=float, default=90.0, help="frames a second (the soak test: 30 fps x 3)")
    parser.add_argument("--work-ms", type=float, default=300.0, help="main-thread time per frame taken")
    parser.add_argument("--frames", type=int, default=30, help="distinct dataset frames sent round and round")
    parser.add_argument("--variant", action="append", choices=VARIANTS, help="(repeatable; default: all)")
    parser.add_argument("--role", choices=("pub", "sub"), help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.role == "pub":
        publish(args.endpoint, args.frames, args.rate, args.seconds + 5.0)
        return 0
    if args.role == "sub":
        subscribe(args.endpoint, args.seconds, args.work_ms, args.variant[0])
        return 0
    print(
        f"{args.rate:.0f} Hz of 7-Scenes frames for {args.seconds:.0f} s, {args.work_ms:.0f} ms of work per frame "
        f"taken",
        flush=True,
    )
    for variant in args.variant or VARIANTS:
        run_pair(args, variant)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
