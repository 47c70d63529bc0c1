"""Encode / decode speed of the two busiest messages: `Frame` (VGA RGB-D, every frame, to four services) and
`Tracks` (nested candidates, measurements and depth patches, every frame).

    PYTHONPATH=. .venv/bin/python benchmarks/bench_messages.py [--repeat 2000]

`semmap` is imported from PYTHONPATH (no path of its own), so the same script times another checkout's messages:
`PYTHONPATH=../other-checkout python benchmarks/bench_messages.py` (it uses only the API both have). Decode times
are the message itself: images stay encoded (JPEG) until `rgb()`, in both implementations. Prints microseconds
per call in CPU time (median of 5 rounds: robust to a machine shared with other work) and payload sizes.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np

from semmap.core.messages import (
    CandidateUpdate,
    DepthPatch,
    Detection,
    Frame,
    GroundTruthInstance,
    Intrinsics,
    Measurement,
    TrackedBox,
    Tracks,
)

VGA = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)


def _frame() -> Frame:
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:480, 0:640]
    rgb = np.stack([xx % 256, yy % 256, (xx + yy) % 256], axis=-1).astype(np.uint8)
    depth = rng.integers(500, 4000, (480, 640), dtype=np.uint16)
    instances = [GroundTruthInstance(i, "cup", (10.0 * i, 10.0, 10.0 * i + 40, 60.0), 900, False) for i in range(8)]
    return Frame.from_arrays("robot1", 42, 1.4, rgb, depth, 0.001, VGA, np.eye(4), instances)


def _tracks() -> Tracks:
    rng = np.random.default_rng(1)

    def detection(i: int) -> Detection:
        patch = DepthPatch(100, 80, 4, rng.integers(500, 4000, (30, 40), dtype=np.uint16))
        return Detection((100.0 + i, 80.0, 260.0 + i, 200.0), "chair", 0.87, 1.9, patch)

    candidates = [CandidateUpdate(t, "chair", [Measurement(40 + m, 1.3 + m / 30, detection(m), VGA, 0.001)
                                               for m in range(5)], t % 2 == 0) for t in range(6)]
    boxes = [TrackedBox(t, "chair", (10.0 * t, 20.0, 10.0 * t + 50, 90.0), 7, t < 6) for t in range(20)]
    return Tracks("robot1", 42, 1.4, candidates, [3, 9], boxes, "", {"update_ms": 0.4}, 1.39, 1.41)


def _time_us(fn: Callable[[], object], repeat: int) -> float:
    rounds = []
    for _ in range(5):
        start = time.process_time()
        for _ in range(repeat):
            fn()
        rounds.append((time.process_time() - start) / repeat * 1e6)
    return statistics.median(rounds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=2000)
    args = parser.parse_args()
    for name, message in (("Frame", _frame()), ("Tracks", _tracks())):
        payload = message.encode()
        kind = type(message)
        encode_us = _time_us(message.encode, args.repeat)
        decode_us = _time_us(lambda p=payload, k=kind: k.decode(p), args.repeat)
        print(f"{name:7s} {len(payload) / 1024:8.1f} KiB   encode {encode_us:8.1f} us   decode {decode_us:8.1f} us")


if __name__ == "__main__":
    main()
