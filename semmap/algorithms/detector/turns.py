"""Which frames detector replicas detect at a cadence: the turn logic of the detector service, free of I/O.

N replicas share the frame stream in blocks of `every_n` frames (block frame_id // every_n, owned by rank
block % N: `owner`). In a block of its own a replica detects the first frame that reaches it, at least `every_n`
frames after the last one it detected (`ReplicaTurns.skips`); a replica that ran late (its queue handed it a newer
frame) so takes that frame instead of idling until its next block. The frames of its share that its queue passed
over are answered as `dropped` where a detection was lost, or as `stride` where the cadence would have skipped them
anyway (`ReplicaTurns.passed_over`).

`simulate` plays the same logic against a clock: frames arriving at a pace, each detection taking a given time. It
answers what a real-time run detects on a machine whose detector takes that long, without that machine
(benchmarks/bench_schedule.py maps the frames it picks).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass


def owner(frame_id: int, every_n: int, replicas: int) -> int:
    """The rank of the replica that answers `frame_id`: the one owning its block of `every_n` frames.

    Why blocks and not frame_id % replicas: with a cadence the due frames (one a block) must reach every replica
    in turn; by frame id alone, 2 replicas and every 2nd frame would hand all due frames to replica 0."""
    return (frame_id // max(1, every_n)) % max(1, replicas)


@dataclass
class ReplicaTurns:
    """One replica's cadence: whether a frame of its share is detected, and how the frames its queue passed over
    are answered. `last_detected` is the last frame it detected (None: none yet)."""

    every_n: int
    lockstep: bool = False
    last_detected: int | None = None

    def skips(self, frame_id: int, last: int | None = None) -> bool:
        """Lockstep: the first frame of each block of n (every n-th frame by id). Real time: the first frame of
        our block that reaches us, at least n frames after the last one detected (`last`, default the last
        detected), so a detector that ran late takes that frame instead of idling until its next block."""
        if self.every_n <= 1:
            return False
        if self.lockstep:
            return frame_id % self.every_n != 0
        last = self.last_detected if last is None else last
        if last is None:
            return False
        return frame_id // self.every_n == last // self.every_n or frame_id - last < self.every_n

    def passed_over(self, frame_id: int, missed: list[int], detects_frame: bool = False) -> list[tuple[int, str]]:
        """How to answer `missed`, frames of our share that never reached us before `frame_id` did: `dropped` where
        one would have been detected (the first due one of a block), `stride` where the cadence would have skipped
        it anyway or where `frame_id`, of the same block, is detected instead (`detects_frame`: late, not lost).
        So the dropped count is the detections real time cost, not every frame the queue passed over."""
        last = self.last_detected
        block = frame_id // max(1, self.every_n)
        answers: list[tuple[int, str]] = []
        for missed_id in missed:
            late = detects_frame and missed_id // max(1, self.every_n) == block
            if late or self.skips(missed_id, last):
                answers.append((missed_id, "stride"))
                continue
            last = missed_id  # (the one it would have detected: the block's later frames are its stride)
            answers.append((missed_id, "dropped"))
        return answers


def simulate(
    frames: int,
    every_n: int,
    replicas: int,
    detect_s: Callable[[int], float],
    frame_interval_s: float,
) -> list[int]:
    """The frames a real-time run's `replicas` detect, in order: frame k arrives at k * `frame_interval_s`; each
    replica's queue holds the newest frame of its share (the service's `detector.queue: 1`; the others' frames are
    passed over as they arrive, so they never take its place), and it detects a frame of its share
    as `ReplicaTurns.skips` allows, busy for `detect_s(frame_id)` seconds. Why a simulation: which frames get
    detected, not how many, decides what is mapped (evenly spaced detections give more distinct views than the
    same number in pairs), and it follows from the turn logic and the detector's times alone."""
    turns = [ReplicaTurns(every_n) for _ in range(replicas)]
    busy_until = [0.0] * replicas
    waiting: list[int | None] = [None] * replicas  # the newest frame queued while busy
    detected: list[int] = []

    def handle(rank: int, frame_id: int, now: float) -> None:  # (only frames of the replica's share come here)
        if turns[rank].skips(frame_id):
            return
        turns[rank].last_detected = frame_id
        detected.append(frame_id)
        busy_until[rank] = now + max(0.0, detect_s(frame_id))

    for frame_id in range(frames):
        now = frame_id * frame_interval_s
        for rank in range(replicas):
            if owner(frame_id, every_n, replicas) != rank:
                continue
            # a queued frame first, as soon as the detection before it ended (in order of when that was)
            if waiting[rank] is not None and busy_until[rank] <= now:
                queued, waiting[rank] = waiting[rank], None
                handle(rank, queued, busy_until[rank])
            if busy_until[rank] <= now:
                handle(rank, frame_id, now)
            else:
                waiting[rank] = frame_id  # (the older one queued is dropped: the queue keeps the newest)
    for rank in range(replicas):
        if waiting[rank] is not None:
            handle(rank, waiting[rank], busy_until[rank])
    return sorted(detected)
