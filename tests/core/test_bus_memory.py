"""Real-time streams hold a bounded number of frames however slow their reader (in Zenoh's callback channel a
detector 1.5 s a frame behind a 90 Hz stream would hold 256 frames, +235 MB over a soak)."""

from __future__ import annotations

import threading
import time

import numpy as np

from semmap.core.messages import Frame, Intrinsics
from semmap.runtime.orchestrator import free_loopback_port
from semmap.runtime.transport.bus import Bus, BusConfig, LatestSamples, RunTrust

VGA = Intrinsics(525.0, 525.0, 320.0, 240.0, 640, 480)


def test_latest_samples_keep_the_newest_and_count_the_rest() -> None:
    box = LatestSamples(2)
    for i in range(1000):
        box.put(i)
    assert len(box) == 2 and box.dropped == 998
    assert [box.take(0.01), box.take(0.01)] == [998, 999]
    assert box.take(0.01) is None  # (timed out: nothing waits)


def test_closing_wakes_a_waiting_reader() -> None:
    box = LatestSamples(1)
    got: list[object] = []
    reader = threading.Thread(target=lambda: got.append(box.take()))
    reader.start()
    time.sleep(0.05)
    box.close()
    reader.join(2.0)
    assert not reader.is_alive() and got == [None]


def _frame(frame_id: int, rng: np.random.Generator) -> Frame:
    rgb = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
    depth = rng.integers(500, 4000, (480, 640), dtype=np.uint16)  # 614 KB a frame, as 7-Scenes'
    return Frame.from_arrays("memrobot", frame_id, frame_id / 30.0, rgb, depth, 0.001, VGA)


def test_a_stuck_reader_holds_at_most_latest_frames() -> None:
    """200 VGA frames go out while the reader is stuck on its first: it then gets only the newest `latest`,
    the rest are dropped unread (counted), not queued."""
    hub = f"tcp/127.0.0.1:{free_loopback_port()}"
    receiver = Bus(BusConfig(mode="peer", listen=[hub]), "memrobot")
    sender = Bus(BusConfig(mode="peer", connect=[hub], listen=[]), "memrobot")
    try:
        release = threading.Event()
        got: list[int] = []

        def on_frame(frame: Frame) -> None:
            got.append(frame.frame_id)
            release.wait(30.0)  # the first frame keeps the reader busy until every frame was sent

        receiver.subscribe(receiver.keys.frames, Frame, on_frame, latest=2)
        pub = sender.publisher(sender.keys.frames)
        assert pub.wait_matching(10.0)
        rng = np.random.default_rng(0)
        frames = [_frame(i, rng) for i in range(8)]
        # frame 0 first, until the reader holds it: a route that is still being set up may lose the first puts
        # (seen as got[0] == 3 on a busy machine), which would say nothing about the reader's queue
        deadline = time.monotonic() + 10.0
        zero_puts = 0
        while not got and time.monotonic() < deadline:
            frames[0].frame_id = 0
            pub.put(frames[0])
            zero_puts += 1
            time.sleep(0.2)
        assert got, "frame 0 never arrived"
        for i in range(1, 200):
            frame = frames[i % len(frames)]
            frame.frame_id = i
            pub.put(frame)
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline and (not got or sum(receiver.dropped.values()) + 3 < 200):
            time.sleep(0.05)
        waiting = receiver._boxes["frames"]
        assert len(waiting) <= 2, "never more than `latest` frames wait"
        release.set()
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and (len(waiting) or got[-1] != 199):
            time.sleep(0.05)
        assert got[0] == 0 and got[-1] == 199, got
        assert len(got) <= 1 + 2, got  # the stuck one, then only the newest two
        # every frame read or counted as dropped (a repeated frame 0 that was in flight counts too)
        assert 200 <= len(got) + receiver.dropped["frames"] <= 199 + zero_puts
    finally:
        release.set()
        sender.close()
        receiver.close()


def test_frames_a_reader_does_not_want_never_take_the_place_of_one_it_does() -> None:
    """A detector replica takes only its share (`wanted`): the others' frames are passed over as they arrive,
    before the signature check and the queue, so the newest frame *of its share* waits for it, and nothing it
    passed over counts as dropped. A forged frame it wants is still refused and counted."""
    hub = f"tcp/127.0.0.1:{free_loopback_port()}"
    secret = bytes.fromhex(RunTrust.new_secret())
    receiver = Bus(BusConfig(mode="peer", listen=[hub]), "memrobot", RunTrust("run1", secret, "detector"))
    sender = Bus(BusConfig(mode="peer", connect=[hub], listen=[]), "memrobot", RunTrust("run1", secret, "player"))
    forger = Bus(BusConfig(mode="peer", connect=[hub], listen=[]), "memrobot",
                 RunTrust("run1", bytes.fromhex(RunTrust.new_secret()), "player"))
    release = threading.Event()
    try:
        got: list[int] = []
        plain: list[int] = []

        def on_frame(frame: Frame) -> None:
            got.append(frame.frame_id)
            release.wait(30.0)  # the first frame keeps the reader busy until the rest were sent

        ours = (lambda frame_id: frame_id % 4 < 2)  # noqa: E731 - replica 0 of 2, every 2nd frame: 0-1, 4-5, 8-9
        receiver.subscribe(receiver.keys.frames, Frame, on_frame, latest=1, wanted=ours)
        receiver.subscribe(receiver.keys.frames, Frame, lambda frame: plain.append(frame.frame_id), wanted=ours)
        pub, forged = sender.publisher(sender.keys.frames), forger.publisher(forger.keys.frames)
        assert pub.wait_matching(10.0) and forged.wait_matching(10.0)
        rng = np.random.default_rng(0)
        frame = _frame(0, rng)
        deadline = time.monotonic() + 10.0
        zero_puts = 0
        while not got and time.monotonic() < deadline:  # (a route still being set up may lose the first puts)
            pub.put(frame)
            zero_puts += 1
            time.sleep(0.2)
        assert got == [0], "frame 0 never arrived"
        for i in range(1, 12):  # 4, 5, 8, 9 are ours; 10 and 11, the newest, are not
            frame.frame_id = i
            pub.put(frame)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and len(plain) < 6 + len(got):  # (frame 0 may have come more than once)
            time.sleep(0.05)
        time.sleep(0.2)
        release.set()
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and len(got) < 2:
            time.sleep(0.05)
        assert got == [0, 9], "the newest frame of its share waited, not frame 11 of the other replica"
        # 1, 4, 5 and 8 were dropped for 9 (and a frame 0 put again while the first was in flight); the others'
        # frames were not counted
        assert 4 <= receiver.dropped["frames"] <= 3 + zero_puts
        assert sorted(set(plain)) == [0, 1, 4, 5, 8, 9]
        for i in (12, 14):  # forged: 12 is ours (refused and counted by both readers), 14 is not (passed over)
            frame.frame_id = i
            forged.put(frame)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and sum(receiver.rejected.values()) < 2:
            time.sleep(0.05)
        time.sleep(0.2)
        assert receiver.rejected == {"rejected_bad_signature[frames]": 2}, receiver.rejected
        assert got == [0, 9] and 12 not in plain
    finally:
        release.set()
        for bus in (forger, sender, receiver):
            bus.close()
